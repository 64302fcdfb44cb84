"""The trajectory-centric learner of one condition (docs/ALGORITHM.md sections 3-5).

Each iteration: sample N rollouts of the acting controller, fit time-varying linear
dynamics with the GMM prior, expand the cost around the samples, and take the C-step

    p_cur <- argmin_p E_p[sum_t l(x_t, u_t)]  s.t.  KL(p || p_bar) <= epsilon   (paper eq. 7)

with p_bar = p_pre (the linearised global policy) when there is one, else the previous
p_cur (the classic trust region).  epsilon = kl_step * step_mult * T, and step_mult adapts
from the predicted against the actual improvement of the expected cost.

A step is rejected when its samples cost more on average than those of the last accepted
iteration, by more than ``reject_z`` standard errors of the difference of the two means, or
when one of them costs more than holding the start pose does (a rollout worse than that has
diverged; the hold's cost is the first iteration's mean, or the model's prediction when the
first controller is planned on the model): p_cur returns to the controller that drew the
accepted samples and the C-step is taken again from the accepted fit with the step size at
most halved (a line search on epsilon). A step taken at the smallest multiplier is accepted: its
samples re-measure the cost. A first controller planned on the model whose samples all cost more
than the hold is predicted to is dropped before any fit: the hold acts next.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.controllers import hold_controller, smoothed_noise
from lolgps_torch.cost.l12 import to_quadratic
from lolgps_torch.data.records import IdentifiedRecord, IterationRecord
from lolgps_torch.dynamics import DynamicsConfig, DynamicsFitter
from lolgps_torch.dynamics.parameters import ArmParameters, IdentifyConfig
from lolgps_torch.errors import NumericalError, check_fields
from lolgps_torch.policy.actor import controller_actor
from lolgps_torch.task import ArmModel, PegTask
from lolgps_torch.trajopt import (
    CStepConfig,
    adapt_step_mult,
    c_step,
    kl_bound,
    laplace_cost,
    plan_on_model,
)
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost, Trajectories


@dataclass(frozen=True)
class LocalConfig:
    """Settings of the per-condition learner.

    :param samples: rollouts per iteration (N).
    :param init_variance: initial exploration variance, in (torque / effective inertia)^2
        (the inertia including the damping over the noise's correlation time, see
        :func:`initial_controller`),
        i.e. joint accelerations (rad/s^2)^2, so one value fits arms of any size.
    :param init_omega: natural frequency (rad/s) of the soft PD hold of the start pose;
        gains ``kp = m omega^2``, ``kd = 2 m omega`` with m each joint's effective inertia.
    :param noise_smoothing: width (steps) of the Gaussian filter on the exploration noise.
    :param reject_z: a step is rejected when its samples' mean total cost exceeds the last
        accepted iteration's by more than ``reject_z * sqrt(s_new^2 / N + s_acc^2 / N)`` (s the
        sample standard deviations of the total costs): only an increase that the N samples
        can tell from noise undoes a step (0: any increase does).
    :param model_plans: C-steps taken on the arm's model before the first sample
        (:func:`planned_controller`; 0: the first iteration samples the hold controller), with
        either dynamics prior: with the GMM prior too the teachers then follow the cost's
        descent over the mouth within mm, where from the hold they came down 10-50 mm beside
        it and the global policy lost positions under a payload (docs/RESULTS.md at c902895, section 8).
    :param identify: with the model prior, identify the arm's physical parameters from the
        free-space transitions of the rollouts so far before learning each condition
        (:mod:`lolgps_torch.dynamics.identify`): the planned start and the model prior then
        use the identified arm instead of its URDF.
    :param cstep: the C-step's settings.
    :param dynamics: the dynamics fit's settings; its prior is the arm's model by default (a
        fitter alone has no model, so :class:`DynamicsConfig`'s own default is the GMM's).
    """

    samples: int = 5
    init_variance: float = 4.0
    init_omega: float = 2.0
    noise_smoothing: float = 2.0
    reject_z: float = 2.0
    model_plans: int = 10
    identify: bool = False
    cstep: CStepConfig = field(default_factory=CStepConfig)
    dynamics: DynamicsConfig = field(default_factory=lambda: DynamicsConfig(prior="model"))

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "samples": self.samples >= 2,
                "init_variance": 0.0 < self.init_variance < math.inf,
                "init_omega": 0.0 <= self.init_omega < math.inf,
                "noise_smoothing": 0.0 <= self.noise_smoothing < math.inf,
                "reject_z": 0.0 <= self.reject_z < math.inf,
                "model_plans": self.model_plans >= 0,
            },
        )


class Fit(NamedTuple):
    """What one iteration learned about its condition: the sampled controller, the dynamics
    and the cost expansion around its samples."""

    controller: LinearGaussian
    dynamics: LinearDynamics
    cost: QuadraticCost


class Accepted(NamedTuple):
    """The last accepted iteration: its fit, the Laplace estimate of its controller's
    expected cost under that fit, the p_cur that drew its samples, their mean total cost and its
    squared standard error, and their states ``[N, T, dX]`` (p_pre is linearised around them)."""

    fit: Fit
    expected: float
    p_cur: LinearGaussian
    cost: float
    cost_se2: float
    x: Tensor


def initial_controller(task: PegTask, config: LocalConfig) -> LinearGaussian:
    """Soft PD hold of q0 with exploration noise, both scaled per joint by the inertia the joint
    presents over the noise's correlation time ``tau = noise_smoothing dt``:

        ``m_j = 1 / (M(q0)^-1)_jj + b_j tau``

    with b_j the joint's damping.  A torque held for tau changes the joint's velocity by about
    ``torque tau / m_j`` whether inertia or damping resists it, so the same ``init_variance``
    explores every joint of every arm alike; with inertia alone, a heavily damped joint (the
    published xArm7's b / m reaches 600 per second) hardly moved under its noise and its
    controllers took 14-25 iterations against 11-12 (docs/HISTORY.md [R16])."""
    tau = config.noise_smoothing * task.config.world.dt
    m = task.effective_inertia() + task.joint_damping() * tau
    lay = task.layout
    return hold_controller(
        task.T,
        lay.dX,
        lay.q,
        lay.qd,
        task.q0,
        kp=m * config.init_omega**2,
        kd=2.0 * m * config.init_omega,
        variance=config.init_variance * m**2,
    )


def planned_controller(
    task: PegTask | ArmModel, targets: Tensor, hold: LinearGaussian, config: LocalConfig
) -> tuple[LinearGaussian, float]:
    """The hold controller's mean replanned on the arm's model (:func:`.trajopt.plan_on_model`,
    ``config.model_plans`` C-steps of the largest step size), and the hold's total cost.

    Under the model the hold rests at the start state ``x_0 = [q0; 0; P(q0) - p*; 0]``: the
    gravity compensation holds q0 exactly and the PD terms are zero, so the planning starts from
    ``xbar_t = x_0``, ``ubar_t = 0`` and the hold's cost is ``sum_t l(x_0, 0)``."""
    lay, T = task.layout, task.T
    x0 = torch.zeros(lay.dX, dtype=torch.float64, device=task.device)
    x0[lay.q] = task.q0
    x0[lay.points] = (task.kinematics.points(task.q0) - targets).flatten()
    x = x0.expand(T, lay.dX)
    u = hold.mean_action(x)
    rest = float(task.cost.evaluate(x[None], u[None], targets).sum())

    def expand(x: Tensor, u: Tensor) -> QuadraticCost:
        return to_quadratic(task.cost.expand(x[None], u[None], targets), x[None], u[None])

    epsilon = kl_bound(config.cstep.step_mult_max, T, config.cstep)
    planned = plan_on_model(
        task.model.linearize, expand, hold, x, u, config.model_plans, epsilon, config.cstep,
        config.dynamics.initial_state_var,
    )  # fmt: skip
    return planned, rest


# planned_controller's signature: (task, targets, hold, config) -> (first controller, hold's cost)
Planner = Callable[[PegTask, Tensor, LinearGaussian, LocalConfig], tuple[LinearGaussian, float]]


def mean_and_se2(totals: Tensor) -> tuple[float, float]:
    """The mean of the samples' total costs ``[N]`` and its squared standard error
    ``s^2 / N`` (s^2 the unbiased sample variance)."""
    return float(totals.mean()), float(totals.var() / totals.numel())


def step_rejected(totals: Tensor, last: Accepted, start_cost: float, z: float) -> bool:
    """Whether samples with total costs ``totals [N]`` undo the step that drew them:

        mean(totals) - J_acc > z sqrt(s^2 / N + s_acc^2 / N)   or   max(totals) > J_start

    with J_acc, s_acc^2 / N the accepted samples' mean and squared standard error and J_start
    the cost of holding the start pose: an increase the samples' noise
    cannot explain, or one rollout worse than holding still, which only a diverging
    controller gives."""
    cost, se2 = mean_and_se2(totals)
    return cost - last.cost > z * math.sqrt(se2 + last.cost_se2) or float(totals.max()) > start_cost


Report = Callable[[IdentifiedRecord], None]


def identified_record(
    condition: int, params: ArmParameters, errors: tuple[float, float, float, int]
) -> IdentifiedRecord:
    """The record of the arm ``params`` identified for ``condition``, with the one-step errors
    (identified, URDF, plant, transitions) of :meth:`PegTask.one_step_errors`."""
    return IdentifiedRecord(
        condition=condition,
        payload=float(params.payload),
        payload_com=params.payload_com.tolist(),
        compensation=float(params.compensation),
        mass_scale=params.mass_scale.tolist(),
        error_identified=errors[0],
        error_urdf=errors[1],
        error_plant=errors[2],
        transitions=errors[3],
        own_compensation=float(params.own),
    )


class LocalLearner:
    """p_cur, its dynamics model and its step size, for one condition (a hole offset)."""

    def __init__(
        self,
        task: PegTask,
        offset: tuple[float, float],
        config: LocalConfig,
        seed: int,
        report: Report | None = None,
        condition: int = 0,
        planner: Planner = planned_controller,
        limits: tuple[float, float] | None = None,
    ) -> None:
        """``report`` receives the arm identified for condition ``condition`` (with
        ``config.identify``), measured on the condition's first rollouts; ``planner`` gives
        :func:`planned_controller`'s result (with ``config.model_plans``),
        computed here or ahead of time (:class:`~lolgps_torch.lolgps.plans.PlannedStarts`);
        with ``limits`` (share, margin) the samples' actions are kept within the arm's limits
        as the policy's are (:class:`~lolgps_torch.policy.actor.LimitedActor`)."""
        self.task, self.offset, self.config, self.limits = task, offset, config, limits
        self.generator = torch.Generator().manual_seed(seed)
        self.targets = task.targets([offset])[0]
        self.hold = self.p_cur = initial_controller(task, config)
        self.start_cost = math.inf  # the hold's mean total cost, measured by the first samples
        self.planned = False  # whether p_cur is still the controller planned on the model
        model = config.dynamics.prior == "model"
        self.identified = (
            task.identify_model(IdentifyConfig()) if model and config.identify else None
        )
        self.report, self.condition = report, condition
        self.fitter = DynamicsFitter(config.dynamics, task.model.linearize if model else None)
        start = time.perf_counter()
        if config.model_plans > 0:
            try:
                self.p_cur, self.start_cost = planner(task, self.targets, self.p_cur, config)
                self.planned = True
            except NumericalError as error:  # the hold is a safe start: learn from it
                warnings.warn(
                    f"hole {offset}: the first controller could not be planned on the arm's "
                    f"model ({error}); starting from the hold",
                    stacklevel=2,
                )
        self.plan_time = time.perf_counter() - start  # s, logged with the first C-step
        self.step_mult = config.cstep.step_mult_init
        self.accepted: Accepted | None = None

    def sample(self, p_act: LinearGaussian) -> Trajectories:
        """N rollouts of ``p_act`` at this condition (within the arm's limits, with
        ``limits``)."""
        T, dU = self.task.T, self.task.layout.dU
        noise = smoothed_noise(
            self.config.samples, T, dU, self.config.noise_smoothing, self.generator
        ).to(self.task.device)
        actor = controller_actor(p_act, noise, self.task.model, self.limits)
        samples = self.task.sample(actor, [self.offset] * self.config.samples)
        if self.config.identify:
            if self.identified is not None and self.report is not None:  # once: unseen rollouts
                errors = self.task.one_step_errors(samples)
                self.report(identified_record(self.condition, self.identified, errors))
                self.identified = None
            self.task.record(samples)
        return samples

    def planned_start_diverged(self, samples: Trajectories) -> bool:
        """Whether every one of ``samples`` of the controller planned on the model cost more
        than holding the start pose is predicted to (a model wrong enough to mislead the plan,
        e.g. one that allows for a command delay the arm does not have); if so, p_cur becomes
        the hold, whose first samples then measure the start cost, as without a plan."""
        if not self.planned or self.accepted is not None:
            return False
        self.planned = False
        cost = float(samples.cost.sum(1).min())
        if cost <= self.start_cost:
            return False
        warnings.warn(
            f"hole {self.offset}: every sample of the controller planned on the arm's model did "
            f"worse than holding the start pose (the best cost {cost:.1f} > {self.start_cost:.1f});"
            " starting from the hold",
            stacklevel=2,
        )
        self.p_cur, self.start_cost = self.hold, math.inf
        return True

    def fit(self, p_act: LinearGaussian, samples: Trajectories) -> Fit:
        """Dynamics and cost expansion around the new samples; adapts the step size.

        Returns the fit for the C-step: the new one, or, when :func:`step_rejected`, the last
        accepted iteration's fit, with p_cur back at the controller that drew its samples (the
        step is retried at most half as large). A step taken at the smallest multiplier is
        accepted whatever its cost: p_cur is then close to the accepted controller, and its
        samples re-measure that controller's cost (a lucky low draw of the accepted cost would
        otherwise reject every later step). The dynamics and the cost are fitted to the
        samples the arm's controller did not stop (:func:`moved`); the step is judged by all."""
        moving = moved(samples)
        dynamics = self.fitter.update(moving.x, moving.u)
        expansion = self.task.cost.expand(moving.x, moving.u, self.targets)
        fit = Fit(p_act, dynamics, to_quadratic(expansion, moving.x, moving.u))
        expected = float(laplace_cost(p_act, dynamics, fit.cost))
        totals = samples.cost.sum(1)
        last = self.accepted
        if last is not None:
            tried = self.step_mult  # the multiplier of the step that drew these samples
            predicted = laplace_cost(p_act, last.fit.dynamics, last.fit.cost)
            self.step_mult = adapt_step_mult(
                tried, last.expected, predicted, expected, self.config.cstep
            )
            smallest = tried <= self.config.cstep.step_mult_min
            if not smallest and step_rejected(totals, last, self.start_cost, self.config.reject_z):
                # retried at most half as large, whatever the new fit predicts
                self.step_mult = max(
                    min(self.step_mult, tried / 2), self.config.cstep.step_mult_min
                )
                self.p_cur = last.p_cur
                return last.fit
        elif math.isinf(self.start_cost):  # the first samples are the hold's
            self.start_cost = float(totals.mean())
        cost, cost_se2 = mean_and_se2(totals)
        self.accepted = Accepted(fit, expected, self.p_cur, cost, cost_se2, moving.x)
        return fit

    def improve(self, fit: Fit, p_bar: LinearGaussian) -> tuple[float, float, float]:
        """The C-step against ``p_bar``; returns (epsilon, eta, KL)."""
        epsilon = kl_bound(self.step_mult, self.task.T, self.config.cstep)
        result = c_step(fit.cost, fit.dynamics, p_bar, epsilon, self.config.cstep)
        self.p_cur = result.policy
        return epsilon, float(result.eta), float(result.kl.sum())


Linearizer = Callable[[Tensor], LinearGaussian]


def moved(samples: Trajectories) -> Trajectories:
    """The samples the arm's controller did not stop at a limit (all of them where it stopped
    every one): a stopped arm stays braked whatever it is commanded, so the rest of its
    rollout is no evidence of the dynamics."""
    if bool(samples.fault.all()):
        return samples
    return Trajectories(*(field[~samples.fault] for field in samples))


def iterate(
    learner: LocalLearner,
    p_act: LinearGaussian,
    linearize: Linearizer | None,
    anchor_to_pre: bool,
    where: tuple[int, int, float],
) -> tuple[Trajectories, LinearGaussian | None, IterationRecord]:
    """One iteration of the trajectory-centric loop, shared by the stream, batch GPS and the
    single-condition learner: sample ``p_act``, fit the dynamics, linearise the global policy
    into p_pre around the accepted samples (the new ones unless the step was rejected; when
    ``linearize`` is given) and take the C-step against p_pre (``anchor_to_pre``) or against
    the previous p_cur.

    :param where: (condition, iteration, alpha of p_act) for the record.
    :returns: the samples, the new p_pre (None without ``linearize``) and the iteration's record,
        whose C-step time at iteration 0 includes the C-steps planned on the model before it.
    """
    t0 = time.perf_counter()
    samples = learner.sample(p_act)
    t1 = time.perf_counter()
    if learner.planned_start_diverged(samples):  # no fit or C-step: the hold acts next
        times = (t1 - t0, 0.0, learner.plan_time)
        record = iteration_record(where, samples, (0.0, 0.0, 0.0), learner.step_mult, times)
        return samples, None, record
    fit = learner.fit(p_act, samples)
    assert learner.accepted is not None  # fit accepts the first iteration
    p_pre = linearize(learner.accepted.x) if linearize is not None else None
    t2 = time.perf_counter()
    epsilon, eta, kl = learner.improve(
        fit, p_pre if p_pre is not None and anchor_to_pre else learner.p_cur
    )
    t3 = time.perf_counter() + (learner.plan_time if where[1] == 0 else 0.0)
    record = iteration_record(where, samples, (epsilon, eta, kl), learner.step_mult,
                              (t1 - t0, t2 - t1, t3 - t2))  # fmt: skip
    return samples, p_pre, record


def iteration_record(
    where: tuple[int, int, float],
    samples: Trajectories,
    cstep: tuple[float, float, float],
    step_mult: float,
    times: tuple[float, float, float],
) -> IterationRecord:
    """The record of one iteration: ``where`` (condition, iteration, alpha), its samples'
    statistics, the C-step's (epsilon, eta, KL), and its sampling, fit and C-step times."""
    condition, iteration, alpha = where
    epsilon, eta, kl = cstep
    return IterationRecord(
        condition=condition,
        iteration=iteration,
        alpha=alpha,
        mean_cost=float(samples.cost.sum(1).mean()),
        mean_distance=float(samples.final_distance.mean()),
        best_distance=float(samples.final_distance.min()),
        success_rate=float(samples.success.double().mean()),
        faults=int(samples.fault.sum()),
        epsilon=epsilon,
        eta=eta,
        kl=kl,
        step_mult=step_mult,
        time_sample=times[0],
        time_fit=times[1],
        time_cstep=times[2],
    )
