"""The C-step iterated on a model before any sample (docs/ALGORITHM.md section 4.2): against
the Riccati recursion on a linear system, its trust region, an independent optimum of a
nonlinear system by the system's own rollout, and the model-planned first controller of the peg
task on the KUKA and on published descriptions, with its fallback to the hold."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace

import pytest
import torch
from torch import Tensor

from lolgps_torch.controllers import trajectory_kl
from lolgps_torch.errors import NumericalError
from lolgps_torch.lolgps import local
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
from lolgps_torch.robot.validate import ArmWarning
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.simulator import WorldConfig
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.trajopt import CStepConfig, plan_on_model
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost, StepLinearizer
from tests.test_cstep import random_problem, riccati
from tests.test_published import PUBLISHED

DT = torch.float64

UNLIMITED = PlantConfig(limits="off")  # an arm whose controller lets it pass its limits


Step = Callable[[int, Tensor, Tensor], Tensor]  # (t, x, u) -> x'


def _mean_trajectory(p: LinearGaussian, x0: Tensor, step: Step) -> tuple[Tensor, Tensor]:
    """The mean trajectory ``[T, dX], [T, dU]`` of ``p`` under the deterministic ``step``
    (with ``x_T``, after the last action: ``[T + 1, dX]``)."""
    xs, us = [x0], []
    for t in range(p.T):
        us.append(p.K[t] @ xs[-1] + p.k[t])
        xs.append(step(t, xs[-1], us[-1]))
    return torch.stack(xs), torch.stack(us)


def _linear(dynamics: LinearDynamics) -> tuple[Step, StepLinearizer]:
    """The linear system as a model: its step (the last action moves nothing), and a
    linearizer returning its own F, f."""

    def step(t: int, x: Tensor, u: Tensor) -> Tensor:
        last = t >= dynamics.F.shape[0]
        return x if last else dynamics.F[t] @ torch.cat([x, u]) + dynamics.f[t]

    def linearize(x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        assert x.shape[0] == dynamics.F.shape[0]
        return dynamics.F, dynamics.f

    return step, linearize


def _expansion(cost: QuadraticCost) -> Callable[[Tensor, Tensor], QuadraticCost]:
    return lambda x, u: cost


def test_a_linear_system_is_planned_to_its_lqr_in_one_unbounded_round() -> None:
    """On a linear system with a quadratic cost the linearisation is exact: one round with a
    bound that does not bind gives the Riccati recursion's gains, with the start's covariance."""
    cost, dynamics, start = random_problem(seed=3)
    step, linearize = _linear(dynamics)
    x, u = _mean_trajectory(start, dynamics.x0_mean, step)
    x = x[:-1]
    planned = plan_on_model(linearize, _expansion(cost), start, x, u, 1, 1e6, CStepConfig())
    K, k = riccati(cost, dynamics)
    torch.testing.assert_close(planned.K, K, rtol=0.0, atol=1e-6)
    torch.testing.assert_close(planned.k, k, rtol=0.0, atol=1e-6)
    assert planned.cov is start.cov


@pytest.mark.parametrize("epsilon", [2.0, 10.0])
def test_each_round_stays_inside_its_trust_region(epsilon: float) -> None:
    """One round moves the controller by KL(p_1 || p_0) <= (1 + tol) epsilon under the
    linearisation it was taken on."""
    cost, dynamics, start = random_problem(seed=4)
    step, linearize = _linear(dynamics)
    x, u = _mean_trajectory(start, dynamics.x0_mean, step)
    x = x[:-1]
    config = CStepConfig()
    planned = plan_on_model(linearize, _expansion(cost), start, x, u, 1, epsilon, config)
    exact = dynamics._replace(cov=1e-6 * torch.eye(6, dtype=DT).expand_as(dynamics.cov),
                              x0_cov=1e-6 * torch.eye(6, dtype=DT))  # fmt: skip
    kl = float(trajectory_kl(planned, start, exact).sum())
    assert 0.5 * epsilon < kl <= (1 + config.kl_tolerance) * epsilon


def test_rounds_on_a_nonlinear_system_reach_its_optimum_by_its_own_rollout() -> None:
    """A damped double pendulum-like system driven by torques (nonlinear gravity terms) starts
    at rest 1.1 rad from its goal. The planned controller, rolled out on the nonlinear system
    itself, costs what the open-loop optimum found by L-BFGS on that rollout costs (an
    independent answer), although the rounds only saw linearisations along predicted, not
    simulated, trajectories."""
    T, dt = 60, 0.05
    goal = torch.tensor([1.0, -0.5], dtype=DT)

    def step(x: Tensor, u: Tensor) -> Tensor:
        q, qd = x[..., :2], x[..., 2:]
        qd = qd + dt * (u - 4.0 * torch.sin(q) - 0.5 * qd)
        return torch.cat([q + dt * qd, qd], -1)

    def linearize(x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        xu = torch.cat([x, u], -1)
        F = torch.func.vmap(torch.func.jacrev(lambda z: step(z[:4], z[4:])))(xu)
        return F, step(x, u) - (F @ xu[..., None]).squeeze(-1)

    C = torch.diag(torch.tensor([1.0, 1.0, 0.01, 0.01, 1e-3, 1e-3], dtype=DT)).repeat(T, 1, 1)
    C[-1, :2, :2] *= 100.0
    target = torch.cat([goal, torch.zeros(2, dtype=DT)])  # the goal at rest, u = 0
    offset = 0.5 * torch.einsum("i,tij,j->t", target, C[:, :4, :4], target)
    cost = QuadraticCost(C, -C[:, :, :4] @ target, offset)  # 1/2 (y - y*)^T C (y - y*)

    def total(x: Tensor, u: Tensor) -> Tensor:
        y = torch.cat([x, u], -1)
        return 0.5 * torch.einsum("ti,tij,tj->", y, C, y) + (cost.c * y).sum() + cost.cc.sum()

    x0 = torch.zeros(4, dtype=DT)
    start = LinearGaussian(torch.zeros(T, 2, 4, dtype=DT), torch.zeros(T, 2, dtype=DT),
                           0.1 * torch.eye(2, dtype=DT).expand(T, 2, 2))  # fmt: skip
    x, u = _mean_trajectory(start, x0, lambda t, x, u: step(x, u))
    planned = plan_on_model(linearize, _expansion(cost), start, x[:-1], u, 15, 200.0, CStepConfig())
    x, u = _mean_trajectory(planned, x0, lambda t, x, u: step(x, u))
    achieved = float(total(x[:-1], u))

    actions = torch.zeros(T, 2, dtype=DT, requires_grad=True)
    optimiser = torch.optim.LBFGS([actions], max_iter=500, tolerance_grad=1e-10,
                                  line_search_fn="strong_wolfe")  # fmt: skip

    def closure() -> Tensor:
        optimiser.zero_grad()
        xs = [x0]
        for t in range(T - 1):
            xs.append(step(xs[-1], actions[t]))
        value = total(torch.stack(xs), actions)
        value.backward()
        return value

    optimiser.step(closure)
    optimum = float(closure().detach())
    assert float(total(x[:1].expand(T, 4), torch.zeros(T, 2, dtype=DT))) > 10 * optimum
    assert achieved == pytest.approx(optimum, rel=1e-3)


def test_the_model_prior_plans_a_first_controller_that_inserts_the_peg() -> None:
    """On the KUKA, the first iteration's samples of the hold controller all end far from the
    hole; the first controller is planned on the arm's model (with the GMM prior the same), and its
    samples, drawn in the simulator with contact, already succeed. The hold's cost, which
    judges a rollout diverged, is then the cost of resting at the start pose: less than the
    hold's exploring samples cost, and far more than the planned samples'. The plan's time is
    logged with the first iteration's C-step."""
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=5)
    try:
        model = LocalConfig()
        base = replace(model, dynamics=replace(model.dynamics, prior="gmm"), model_plans=0)
        assert model.dynamics.prior == "model"  # the default
        hold = LocalLearner(task, (0.02, -0.01), base, seed=1)
        planned = LocalLearner(task, (0.02, -0.01), model, seed=1)
        unplanned = LocalLearner(task, (0.02, -0.01), replace(model, model_plans=0), seed=1)
        gmm = LocalLearner(task, (0.02, -0.01), replace(base, model_plans=10), seed=1)
        assert torch.equal(unplanned.p_cur.k, hold.p_cur.k)
        assert torch.equal(gmm.p_cur.k, planned.p_cur.k)  # the plan is the model's either way
        assert torch.equal(hold.p_cur.cov, planned.p_cur.cov)
        assert not torch.equal(hold.p_cur.k, planned.p_cur.k)
        held, _, _ = iterate(hold, hold.p_cur, None, False, (0, 0, 0.0))
        first, _, record = iterate(planned, planned.p_cur, None, False, (0, 0, 0.0))
    finally:
        task.close()
    assert not bool(held.success.any())
    assert int(first.success.sum()) >= 3
    assert 0.5 * hold.start_cost < planned.start_cost < hold.start_cost
    # 3 of 5 samples at least cost a tenth of holding still (an exploring one may be stopped at
    # a limit, or, without the reflex, flung, its speed cost then large)
    assert int((first.cost.sum(1) < 0.1 * planned.start_cost).sum()) >= 3
    assert 0.0 < planned.plan_time <= record.time_cstep  # the plan is logged as C-step time


@pytest.mark.parametrize("name", ["airo-ur3e", "rtb-rx200", "rtb-kr120"])
def test_the_planned_first_controller_inserts_the_peg_on_published_arms(name: str) -> None:
    """Descriptions as published (a UR3e, a 5-DoF Trossen arm, a ROS-Industrial KUKA whose
    efforts are derived): the first samples of the default learner, planned on each arm's
    model, already insert the peg at a hole off the nominal one."""
    urdf, _, ee_link = PUBLISHED[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        task = PegTask(TaskConfig(urdf=str(urdf), ee_link=ee_link, plant=UNLIMITED), n_worlds=5)
    try:
        learner = LocalLearner(task, (0.015, -0.01), LocalConfig(), seed=4)
        samples, _, _ = iterate(learner, learner.p_cur, None, False, (0, 0, 0.0))
    finally:
        task.close()
    assert int(samples.success.sum()) >= 3


def test_a_plan_that_fails_numerically_starts_from_the_hold_with_a_warning(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The plan is a better start, not a requirement: a numerical failure while planning is
    one warning, and the condition is learnt from the hold, whose cost its samples measure."""

    def failing(*args: object) -> LinearGaussian:
        raise NumericalError("Quu is not positive definite even at eta = 1e+10")

    monkeypatch.setattr(local, "plan_on_model", failing)
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=5)
    try:
        with pytest.warns(UserWarning, match="could not be planned.*starting from the hold"):
            learner = LocalLearner(task, (0.0, 0.0), LocalConfig(), seed=0)
        hold = local.initial_controller(task, LocalConfig())
    finally:
        task.close()
    assert torch.equal(learner.p_cur.k, hold.k) and learner.start_cost == float("inf")


def test_a_planned_start_worse_than_holding_still_is_dropped_for_the_hold() -> None:
    """A model that allows for a command delay the arm does not have (10 ms) plans a first
    controller that flings the KUKA (its samples end about 0.9 m from the hole): their mean
    cost is above the hold's predicted cost, so the learner warns, takes no fit or C-step from
    them, and the hold acts next, its samples measuring the start cost; from there the
    condition is learnt."""
    task = PegTask(
        TaskConfig(
            urdf="robots/kuka_peg.urdf", world=WorldConfig(known_delay=0.01), plant=UNLIMITED
        ),
        n_worlds=5,
    )
    try:
        learner = LocalLearner(task, (-0.02, -0.02), LocalConfig(), seed=0)
        predicted = learner.start_cost
        with pytest.warns(UserWarning, match="did worse than holding the start pose"):
            flung, p_pre, record = iterate(learner, learner.p_cur, None, False, (0, 0, 0.0))
        assert float(flung.cost.sum(1).min()) > predicted and p_pre is None
        assert learner.p_cur is learner.hold and learner.accepted is None
        assert record.eta == 0.0 and record.time_fit == 0.0
        held, _, _ = iterate(learner, learner.p_cur, None, False, (0, 1, 0.0))
        assert learner.start_cost == pytest.approx(float(held.cost.sum(1).mean()))
        assert learner.start_cost < float(flung.cost.sum(1).mean()) / 10
        for i in range(2, 7):
            samples, _, _ = iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
    finally:
        task.close()
    assert bool(samples.success.any())
