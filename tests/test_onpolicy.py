"""The policy's own states: the teachers' support (gating), their labels, and the replay of
the labelled rows."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import torch
from test_replay import make_samples

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.errors import NumericalError
from lolgps_torch.lolgps.distillation import Labels
from lolgps_torch.lolgps.onpolicy import PolicyVisits, Teacher, gated_rows, support_distance
from lolgps_torch.policy import GaussianPolicy
from lolgps_torch.state import StateLayout
from lolgps_torch.types import DistillBatch, LinearGaussian, VisitedRows

F64 = torch.float64
LAYOUT = StateLayout(2)  # dX 16, dU 2
T = 4


def _teacher(seed: int = 0) -> tuple[Teacher, LinearGaussian]:
    """A teacher whose D_g is 50 states about a random mean per step, and its p_cur."""
    g = torch.Generator().manual_seed(seed)
    centre = torch.randn(T, LAYOUT.dX, dtype=F64, generator=g)
    x = centre + 0.1 * torch.randn(50, T, LAYOUT.dX, dtype=F64, generator=g)
    A = torch.randn(T, 2, 2, dtype=F64, generator=g)
    p_cur = LinearGaussian(
        torch.randn(T, 2, LAYOUT.dX, dtype=F64, generator=g),
        torch.randn(T, 2, dtype=F64, generator=g),
        A @ A.mT + torch.eye(2, dtype=F64),
    )
    return Teacher.of(3, (0.1, 0.0), x, Labels(p_cur, None, 1)), p_cur


def test_the_support_distance_is_the_rms_of_the_joint_z_scores() -> None:
    teacher, _ = _teacher()
    floor = torch.full((LAYOUT.dX,), 1e-3, dtype=F64)
    x = teacher.mean + 0.3 * torch.randn(5, T, LAYOUT.dX, dtype=F64)
    got = support_distance(x, teacher, LAYOUT, floor)
    # written out: joint angles and velocities only, the points ignored
    n = 2 * LAYOUT.n_joints
    z = (x[..., :n] - teacher.mean[:, :n]) / teacher.std[:, :n]
    assert torch.allclose(got, (z**2).sum(-1).div(n).sqrt())
    moved = x.clone()
    moved[..., LAYOUT.points] += 100.0  # the peg's points do not gate
    assert torch.equal(support_distance(moved, teacher, LAYOUT, floor), got)


def test_a_state_far_from_the_teacher_gets_no_label() -> None:
    teacher, p_cur = _teacher()
    floor = torch.full((LAYOUT.dX,), 1e-3, dtype=F64)
    near = teacher.mean.clone()[None]  # [1, T, dX]: on the teacher's mean path
    far = near.clone()
    far[0, 2, LAYOUT.q] += 10.0 * teacher.std[2, LAYOUT.q]  # step 2 leaves the support
    rows = gated_rows(torch.cat([near, far]), teacher, teacher.labels, LAYOUT, 3.0, floor)
    # all of ``near`` and ``far`` but its step 2
    assert rows.t.tolist() == [0, 1, 2, 3, 0, 1, 3]
    assert rows.condition.tolist() == [3] * 7
    want = torch.einsum("tux,tx->tu", p_cur.K, near[0]) + p_cur.k
    assert torch.allclose(rows.rows.mean_cur[:4], want)
    assert torch.allclose(rows.rows.prec_cur[2], torch.linalg.inv(p_cur.cov[2]))
    assert not rows.rows.has_pre.any()
    # a floor wider than the spread widens the support
    wide = torch.full((LAYOUT.dX,), 10.0, dtype=F64)
    assert gated_rows(far, teacher, teacher.labels, LAYOUT, 3.0, wide).R == T


def test_visited_rows_round_trip_through_the_replay(tmp_path: Path) -> None:
    samples = make_samples(2, T, LAYOUT.dX, 2, True, 0)
    teacher, _ = _teacher()
    floor = torch.full((LAYOUT.dX,), 1e-3, dtype=F64)
    visited = gated_rows(teacher.mean[None], teacher, teacher.labels, LAYOUT, 3.0, floor)
    replay = ReplayBuffer(tmp_path / "replay.h5")
    replay.append_condition(0, (0.0, 0.0), samples, iterations=1, visited=visited)
    replay.append_condition(1, (0.0, 0.0), samples, iterations=1)
    got = replay.read_condition(0).visited
    assert got is not None and replay.read_condition(1).visited is None
    for a, b in zip((*got.rows, got.condition, got.t), (*visited.rows, visited.condition,
                                                          visited.t), strict=True):  # fmt: skip
        assert a.dtype == b.dtype and torch.equal(a, b)
    empty = VisitedRows(DistillBatch(*(f[:0] for f in visited.rows)), visited.t[:0], visited.t[:0])
    replay.append_condition(2, (0.0, 0.0), samples, iterations=1, visited=empty)
    assert replay.read_condition(2).visited is None


class _BlowingUp:
    """A task whose every batch of rollouts blows the simulation up."""

    layout, device, T = LAYOUT, torch.device("cpu"), T

    model = SimpleNamespace(stopping=lambda x: x[..., LAYOUT.qd])  # the brake's model

    def sample(self, actor: object, offsets: object, kind: str) -> None:
        raise NumericalError("the simulation blew up: joint speed 119 rad/s (bound 100)")


def test_a_policy_that_blows_the_simulation_up_misses_everywhere() -> None:
    teacher, _ = _teacher()
    visits = PolicyVisits(_BlowingUp(), noisy=2, gate=3.0, floor=0.005)  # type: ignore[arg-type]
    policy = GaussianPolicy(LAYOUT.dX, LAYOUT.dU)
    seen = visits(policy, [teacher, teacher], seed=0)
    assert seen.distances == [math.inf, math.inf] and seen.visited is None
    assert seen.rollouts == 6  # the noiseless and 2 noisy rollouts at each position
