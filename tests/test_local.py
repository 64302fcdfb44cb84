"""The local learner's step rejection (docs/ALGORITHM.md section 5)."""

from __future__ import annotations

import torch

from lolgps_torch.controllers import trajectory_kl
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
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
        learner = LocalLearner(task, (0.0, 0.0), LocalConfig(), seed=0)
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
