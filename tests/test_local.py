"""The local learner's step rejection (docs/ALGORITHM.md section 5)."""

from __future__ import annotations

import torch

from lolgps_torch.controllers import trajectory_kl
from lolgps_torch.lolgps.local import (
    Accepted,
    Fit,
    LocalConfig,
    LocalLearner,
    iterate,
    mean_and_se2,
    step_rejected,
)
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian


def test_a_step_that_raises_the_cost_is_retried_smaller_from_the_accepted_controller() -> None:
    """After two ordinary iterations, p_cur is replaced by a controller pushing a constant
    torque (a step that went wrong). Its samples cost more than the accepted ones, so the
    learner returns to the controller that drew the accepted samples and takes a smaller
    C-step from it: the new p_cur is within the new bound of that controller, not of the bad
    one, and p_pre would be fitted around the accepted samples."""
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=5)
    try:
        learner = LocalLearner(task, (0.0, 0.0), LocalConfig(model_plans=0), seed=0)
        for i in range(2):
            iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
        accepted = learner.accepted
        assert accepted is not None
        good, step_mult = accepted.p_cur, learner.step_mult
        push = 0.5 * task.effective_inertia() * 40.0  # 40 rad/s^2 on every joint
        p_cur = learner.p_cur
        bad = LinearGaussian(K=p_cur.K, k=p_cur.k + push, cov=p_cur.cov)
        learner.p_cur = bad
        samples, _, record = iterate(learner, bad, None, False, (0, 2, 0.0))
        assert float(samples.cost.sum(1).mean()) > accepted.cost
        assert learner.step_mult < step_mult
        assert learner.accepted is not None and learner.accepted.x is accepted.x
        dynamics = accepted.fit.dynamics
        to_good = float(trajectory_kl(learner.p_cur, good, dynamics).sum())
        to_bad = float(trajectory_kl(learner.p_cur, bad, dynamics).sum())
        assert to_good <= 1.1 * record.epsilon < to_bad
        # the next step is judged against the accepted samples, not the rejected ones
        samples, _, _ = iterate(learner, learner.p_cur, None, False, (0, 3, 0.0))
        assert float(samples.cost.sum(1).mean()) < float(record.mean_cost)
    finally:
        task.close()
    assert torch.isfinite(learner.p_cur.k).all()


def test_a_step_is_undone_only_by_a_cost_increase_beyond_noise_or_by_a_diverged_rollout() -> None:
    """The rejection rule on total costs: five samples of nearly the same controller, one of
    them stuck on the rim (as 5 samples give near convergence), keep the step; a clear increase
    undoes it; so does one rollout that costs more than the hold of the start pose, even when
    the other four make the mean increase look like noise."""
    accepted = torch.tensor([2.0, 2.5, 1.5, 3.0, 2.5], dtype=torch.float64)
    cost, se2 = mean_and_se2(accepted)
    fit = Fit(*(None,) * 3)  # type: ignore[arg-type]  # the rule reads only the costs
    last = Accepted(fit, 0.0, None, cost, se2, torch.zeros(0))  # type: ignore[arg-type]
    start = 220.0
    one_stuck = torch.tensor([2.0, 3.0, 2.5, 40.0, 1.5], dtype=torch.float64)
    worse = torch.tensor([6.0, 7.0, 6.5, 8.0, 7.5], dtype=torch.float64)
    one_diverged = torch.tensor([1.0, 1.5, 1.0, 1.2, 900.0], dtype=torch.float64)
    assert not step_rejected(one_stuck, last, start, z=2.0)
    assert step_rejected(one_stuck, last, start, z=0.0)  # any increase, as before
    assert step_rejected(worse, last, start, z=2.0)
    assert float(one_diverged.mean()) - cost < 2.0 * (mean_and_se2(one_diverged)[1] + se2) ** 0.5
    assert step_rejected(one_diverged, last, start, z=2.0)
