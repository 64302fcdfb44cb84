"""Policy corrections: the policy's own rollouts, cut where they leave the teacher's
trajectories, labelled by the teacher's controllers."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from lolgps_torch.lolgps.corrections import CorrectionConfig, Teacher, teacher_reference, visit
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian

F64 = torch.float64


@pytest.fixture(scope="module")
def task() -> Iterator[PegTask]:
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=2)
    yield task
    task.close()


def _teacher(task: PegTask, policy: GaussianPolicy) -> tuple[Teacher, torch.Tensor]:
    """A teacher whose reference is the policy's own noiseless rollout at the nominal hole."""
    T, dX, dU = task.T, task.layout.dX, task.layout.dU
    x = task.sample(policy_actor(policy), [(0.0, 0.0)]).x
    g = torch.Generator().manual_seed(3)
    p_cur = LinearGaussian(
        0.01 * torch.randn(T, dU, dX, dtype=F64, generator=g),
        torch.randn(T, dU, dtype=F64, generator=g),
        2.0 * torch.eye(dU, dtype=F64).expand(T, dU, dU),
    )
    return Teacher((0.0, 0.0), p_cur, None, teacher_reference(task, x)), x[0]


def test_visited_states_carry_the_teachers_targets(task: PegTask) -> None:
    policy = GaussianPolicy(task.layout.dX, task.layout.dU)
    teacher, x = _teacher(task, policy)
    config = CorrectionConfig(rollouts=2, radius=0.15)
    batch = visit(task, policy, [teacher], config, torch.Generator().manual_seed(0))
    T = task.T
    # the noiseless rollout is the reference itself: all of it is kept, first
    assert batch.M > T and torch.allclose(batch.x[:T], x, atol=1e-6)
    want = torch.einsum("tux,tx->tu", teacher.p_cur.K, batch.x[:T]) + teacher.p_cur.k
    assert torch.allclose(batch.mean_cur[:T], want, atol=1e-12)
    assert torch.allclose(batch.prec_cur, 0.5 * torch.eye(task.layout.dU, dtype=F64))
    assert not batch.has_pre.any()


def test_rollouts_are_cut_where_they_leave_the_reference(task: PegTask) -> None:
    policy = GaussianPolicy(task.layout.dX, task.layout.dU)
    teacher, x = _teacher(task, policy)
    config = CorrectionConfig(rollouts=3, radius=1e-9)
    batch = visit(task, policy, [teacher], config, torch.Generator().manual_seed(0))
    # the noiseless rollout stays on the reference; the noisy ones share only the start state,
    # since the first noisy torque moves them off it
    assert batch.M == task.T + 2
    assert torch.allclose(batch.x[task.T :], x[:1].expand(2, -1), atol=1e-6)
