"""The checked refits of the S-step (keep the best policy by its rollouts, undo the rest), the
choice of the controllers that label D_g, and the kinematic augmentation of D_g's states."""

from __future__ import annotations

import pytest
import torch

from lolgps_torch.lolgps.stream import StreamConfig, StreamLearner, label_source
from lolgps_torch.policy import GaussianPolicy
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian


def _first_weight(policy: GaussianPolicy) -> float:
    return float(next(policy.net.parameters()).detach()[0, 0])


def test_refits_keep_the_best_policy_and_stop_once_all_succeed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    learner = StreamLearner.__new__(StreamLearner)  # no task: scoring and fitting are scripted
    learner.config = StreamConfig(refits=5, refit_steps=7)
    learner.policy = GaussianPolicy(3, 2)
    records: list[dict[str, object]] = []
    learner.log = records.append
    w0 = _first_weight(learner.policy)
    # the initial fit, then one score per refit: better, worse, all three conditions solved
    scores = iter([(1, -0.3), (2, -0.2), (1, -0.1), (3, -0.05)])
    starts: list[tuple[float, int | None]] = []

    def fit(current: list[object], seed: int, steps: int | None = None) -> list[float]:
        starts.append((_first_weight(learner.policy) - w0, steps))
        with torch.no_grad():
            for p in learner.policy.net.parameters():
                p.add_(1.0)
        return [float(len(starts))]

    monkeypatch.setattr(learner, "_distill", fit)
    monkeypatch.setattr(learner, "_score", lambda offsets: next(scores))
    offsets = [(0.0, 0.0), (0.1, 0.0), (0.2, 0.0)]
    best, losses = learner._refit(4, [], offsets, seed=3)

    assert best == (3, -0.05) and losses == [3.0]  # the losses of the fit that was kept
    # each refit starts from the best weights so far: the worse second one was undone
    assert starts == [(0.0, 7), (1.0, 7), (1.0, 7)]
    assert _first_weight(learner.policy) - w0 == pytest.approx(2.0)
    assert [r["kept"] for r in records] == [True, False, True]
    assert all(r["condition"] == 4 and r["of"] == 3 for r in records)


def test_no_refit_when_the_policy_already_succeeds(monkeypatch: pytest.MonkeyPatch) -> None:
    learner = StreamLearner.__new__(StreamLearner)
    learner.config = StreamConfig(refits=3)
    learner.policy = GaussianPolicy(3, 2)
    learner.log = lambda record: pytest.fail(f"unexpected refit {record}")
    monkeypatch.setattr(learner, "_distill", lambda *a, **k: pytest.fail("unexpected fit"))
    monkeypatch.setattr(learner, "_score", lambda offsets: (len(offsets), -0.001))
    assert learner._refit(0, [], [(0.0, 0.0)], seed=0) == ((1, -0.001), None)


def test_d_g_is_labelled_by_a_p_cur_that_succeeded() -> None:
    def controller(gain: float) -> LinearGaussian:
        T, dU, dX = 3, 2, 4
        return LinearGaussian(
            gain * torch.ones(T, dU, dX, dtype=torch.float64),
            torch.zeros(T, dU, dtype=torch.float64),
            torch.eye(dU, dtype=torch.float64).expand(T, dU, dU),
        )

    final = (controller(1.0), controller(2.0), 12)
    sampled = (controller(3.0), None, 9)
    assert label_source(final, True, sampled) is final
    assert label_source(final, False, sampled) is sampled  # the final p_cur misses
    assert label_source(final, False, None) is final  # nothing verified to fall back on


def test_kinematic_augmentation_gives_states_the_arm_can_be_in() -> None:
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=1)
    learner = StreamLearner.__new__(StreamLearner)
    learner.task = task
    lay, gen = task.layout, torch.Generator().manual_seed(0)
    x = torch.randn(4, 3, lay.dX, dtype=torch.float64, generator=gen)
    x[..., lay.q] = task.q0 + 0.1 * x[..., lay.q]
    out = learner._consistent(x, (0.01, -0.02))
    torch.testing.assert_close(out[..., lay.q], x[..., lay.q])
    torch.testing.assert_close(out[..., lay.qd], x[..., lay.qd])
    # points against FK (finite differences of FK for the velocities), not the code's own Jacobian
    expected = task.kinematics.points(x[..., lay.q]) - task.targets([(0.01, -0.02)])[0]
    torch.testing.assert_close(out[..., lay.points], expected.flatten(-2))
    h = 1e-6
    ahead = task.kinematics.points(x[..., lay.q] + h * x[..., lay.qd])
    behind = task.kinematics.points(x[..., lay.q] - h * x[..., lay.qd])
    velocity = ((ahead - behind) / (2 * h)).flatten(-2)
    torch.testing.assert_close(out[..., lay.point_velocities], velocity, atol=1e-6, rtol=1e-6)
    task.close()
