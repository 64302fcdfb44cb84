"""The arm's physical parameters θ (:mod:`lolgps_torch.dynamics.parameters`: body scales, a
payload, damping, friction and the gravity compensation ``c(q)``) identified from its
transitions (:mod:`lolgps_torch.dynamics.transitions`), pulled toward its URDF.

A transition ``(q_0, qd_0) -> (q_1, qd_1)`` over the control step dt under the command u (held
over the step) balances, at the midpoint ``qm = (q_0 + q_1) / 2``, ``qdm = (qd_0 + qd_1) / 2``
with the mean acceleration ``a = (qd_1 - qd_0) / dt``, the torque residual

    ``r = ID_θ(qm, qdm, a) - tau_link(qm, qdm) + (b + Δb) qdm + F tanh(qdm / v_F)
          - clip(u + c(q_0), -effort, effort)``

(ID_θ the recursive Newton-Euler inverse dynamics of the identified bodies, tau_link the
generalised force of the simulator's link damping, b the URDF's joint damping). θ is the MAP
estimate under Gaussian torque noise σ_τ and a Gaussian prior centred on the URDF
(``s = 1``, ``m_p = 0``, ``c_p`` at the peg tip, ``Δb = F = 0``, ``κ = 1``, and ``ρ = 1/2``
with a wide σ, as the learner cannot know which compensation the arm has):

    ``min_θ  sum_t sum_j ψ(r_tj / σ_τ) + sum_i (θ_i - θ0_i)^2 / σ_i^2``

with ψ Huber's loss, ``ψ(z) = z^2`` within ``|z| <= k`` and ``2k|z| - k^2`` beyond
(``IdentifyConfig.outlier``): a transition the rigid-body model does not describe (a joint that
strikes its limit, or a link that touches something, between the two ends of a control step)
pulls θ by at most k, however large its residual. One such transition among the Panda's 245,
a joint 0.08 rad short of its limit at 17 rad/s, left a residual of 11.5 rad/s at the true
parameters where the others' were within 0.05, and drew least squares to a payload 4 % heavy
with a model 10 times as wrong on other rollouts (``scripts/research/identify_noise.py``).

solved by Levenberg-Marquardt: Gauss-Newton steps ``(J^T J + λ diag(J^T J)) δ = -J^T R`` on
the stacked, whitened residuals R, each data residual z replaced by ``sign(z) sqrt(ψ(z))`` so
that ``|R|^2`` is the objective, with the Jacobian J through the torch rigid-body model
(:mod:`lolgps_torch.robot.rigid_body`) by forward-mode differentiation.

Two other forms of the same balance state it as the joint-speed change it leaves over the
control step (``IdentifyConfig.residual``). The midpoint form puts the forward dynamics FD_θ in
place of ID_θ:

    ``r_v = qd_1 - qd_0 - dt FD_θ(qm, qdm, clip(u + c(q_0)) - (b + Δb) qdm - F tanh(qdm / v_F))``

with the same link damping. The default, ``step``, integrates the control step as the simulator
does, ``substeps`` semi-implicit Euler steps of ``h = dt / substeps`` from the observed start
with the applied torque held,

    ``qd <- qd + h FD_θ(q, qd, clip(u + c(q_0)) - (b + Δb) qd - F tanh(qd / v_F))``,
    ``q <- q + h qd``,   ``r_s = qd_1 - qd``,

so that θ at the truth leaves no residual but the sensors' noise: the midpoint form's error of
order dt^2 is absorbed into θ instead (with 1 mrad of noise the KUKA's identified model
predicted the next joint speeds with 2.2 times the error of the true arm's model, 1.04 times
with ``step``; ``scripts/research/identify_noise.py``).
The torque balance multiplies the inertial parameters by the measured acceleration ``a``, so
sensor noise on the joint speeds sits in its regressors (an error that least squares does not
average away: with 1 mrad of noise the KUKA's 1 kg payload came out 12 % light); in ``r_v`` and
``r_s`` the noise is only on the measured side and in the start state.

A command delay. With a known delay of D physics steps (``WorldConfig.known_delay`` to the
nearest physics step: the stream's estimate or ``--known-delay``) the state carries the last
actions, and the transitions carry them as ``commands = (u_t, u_{t-1}, ..., u_{t-h})``;
physics step s of the control step is driven by ``u_{t-j(s)}``,
``j(s) = max(0, ceil((D - s) / substeps))``, the schedule of the world's model
(``ControlStep.late``, :mod:`lolgps_torch.sim.model`, passed as ``TorqueBalance.late``).
The simulator adds the compensation evaluated at the start of the control step to whichever
command acts, so the step residual holds

    ``tau_s = clip(u_{t-j(s)} + c(q_0), -effort, effort)``

in physics step s, and at the truth it is again zero to rounding (PyBullet's transitions 20
and 50 ms late, ``tests/test_identify.py``). The midpoint forms evaluate the dynamics once
and take the torque's mean over the step, ``sum_s tau_s / substeps``: the mean acceleration is
the mean torque's to the same first order in dt as the midpoint itself, and the torque balance
stays linear in the inertial parameters, the step residual's start. They are kept rather than
refused because the step residual starts from the torque balance's estimate. Without a delay
(j = 0 throughout) every residual is the one above, bit for bit. Two approximations are the
world model's too: the state holds each past command as it acted when issued (within the
effort limits, with that step's compensation), so a command clipped then is replayed off by
the change of the compensation; and a learner that adds its own ``g_0`` to its commands
(``WorldConfig.compensate_gravity``) sent it at the angles of the step it issued the command
in, which ``c(q_0)`` takes as the current.

A delay the learner does not know (no action history in the state: ``--no-detect-delay``, or
a delay the stream's estimate misses) leaves u_t held over the whole step, and the fit puts
the delayed response into θ: κ and the payload come out wrong (docs/RESULTS.md at c902895, section 8).

σ (``speed_noise`` or ``torque_noise``) starts the same for every joint; the MAP estimate is
then solved again with each joint's σ_j its residuals' robust scale, ``1.4826 median_t |r_tj|``
(σ for Gaussian noise, and blind to the few transitions ψ discounts; never below the start),
so that noisy or ill-modelled joints weigh no more against the prior than their scatter says.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.dynamics.parameters import (
    ArmParameters,
    IdentifyConfig,
    identified_dynamics,
)
from lolgps_torch.dynamics.transitions import Transitions
from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.robot.rigid_body import ArmDynamics

MAD_TO_SD = 1.4826  # σ of zero-mean Gaussian noise per median of its absolute value


class TorqueBalance(NamedTuple):
    """What the residual needs besides θ and the data: the URDF's dynamics, the actuator
    limits ``[n]``, the control step (s), the simulator's link damping (linear, angular), its
    physics steps per control step and which command drives each of them: ``late[s] = j``,
    physics step s is driven by ``u_{t-j}`` (:attr:`ControlStep.late
    <lolgps_torch.sim.model.ControlStep>` for the world's known delay; empty: by u_t
    throughout, no delay)."""

    dynamics: ArmDynamics
    effort: Tensor
    dt: float
    link_damping: tuple[float, float]
    substeps: int
    late: tuple[int, ...] = ()

    def applied(self, params: ArmParameters, q: Tensor, u: Tensor, own: Tensor) -> Tensor:
        """``clip(u + c(q), -effort, effort)``, ``c(q) = κ ((1 - ρ) g_0(q) + ρ g_θ(q))`` with
        ``own = g_θ(q)``."""
        urdf = self.dynamics.gravity_torque(q)
        gravity = urdf + params.own * (own - urdf)
        torque = u + params.compensation * gravity
        return torch.minimum(torch.maximum(torque, -self.effort), self.effort)

    def schedule(self) -> tuple[int, ...]:
        """j(s) for each physics step s: ``late``, or 0 throughout when it is empty."""
        late = self.late or (0,) * self.substeps
        if len(late) != self.substeps or min(late) < 0:
            raise LolgpsError(
                f"the delay's schedule {late} must name a command (>= 0) for each of the "
                f"{self.substeps} physics steps"
            )
        return late

    def held(self, params: ArmParameters, data: Transitions, dyn: ArmDynamics) -> dict[int, Tensor]:
        """The torque each command that drives a physics step holds, by how many control
        steps back it was issued: ``{j: clip(u_{t-j} + c(q_0), -effort, effort)}``
        (``[B, n]`` each) for every j of :meth:`schedule`; g_θ from ``dyn``, the identified
        arm."""
        late = self.schedule()
        if max(late) >= data.commands.shape[1]:
            raise LolgpsError(
                f"a command {max(late)} control steps back drives the step, but the "
                f"transitions carry {data.commands.shape[1] - 1} past commands"
            )
        own = dyn.gravity_torque(data.q0)
        return {
            j: self.applied(params, data.q0, data.commands[:, j], own) for j in sorted(set(late))
        }

    def residual(
        self, params: ArmParameters, data: Transitions, config: IdentifyConfig, noise: Tensor
    ) -> Tensor:
        """``r / σ: [B, n]``, the torque, speed or step residual as ``config.residual`` says
        (module docstring), with each joint's σ ``noise [n]``."""
        dyn = identified_dynamics(self.dynamics, params)
        held, late = self.held(params, data, dyn), self.schedule()
        if config.residual == "step":
            q, qd, h = data.q0, data.qd0, self.dt / self.substeps
            for j in late:
                applied = held[j]
                frames = dyn.frames(q)
                wrench = dyn.link_damping(frames, qd, *self.link_damping)
                resisting = dyn.joint_damping * qd + params.friction * torch.tanh(
                    qd / config.friction_speed
                )
                qd = qd + h * dyn.forward_dynamics_at(frames, qd, applied - resisting, wrench)
                q = q + h * qd
            return (data.qd1 - qd) / noise
        # the midpoint forms: the torque's mean over the control step
        if len(held) == 1:
            (applied,) = held.values()
        else:
            parts = [late.count(j) / self.substeps * tau for j, tau in held.items()]
            applied = torch.stack(parts).sum(0)
        qm, qdm = (data.q0 + data.q1) / 2, (data.qd0 + data.qd1) / 2
        frames = dyn.frames(qm)
        wrench = dyn.link_damping(frames, qdm, *self.link_damping)
        resisting = dyn.joint_damping * qdm + params.friction * torch.tanh(
            qdm / config.friction_speed
        )
        if config.residual == "speed":
            qdd = dyn.forward_dynamics_at(frames, qdm, applied - resisting, wrench)
            return (data.qd1 - data.qd0 - self.dt * qdd) / noise
        needed = dyn.inverse_dynamics_at(frames, qdm, (data.qd1 - data.qd0) / self.dt, wrench)
        return (needed + resisting - applied) / noise


def objective(
    balance: TorqueBalance,
    prior: ArmParameters,
    data: Transitions,
    config: IdentifyConfig,
    theta: Tensor,
    noise: Tensor | None = None,
) -> Tensor:
    """The stacked residuals R(θ), the data's whitened and under Huber's loss
    (:func:`robust`), then the prior's: ``|R|^2`` the MAP objective, with each joint's σ
    ``noise [n]`` (default: ``config.noise_floor``)."""
    params = prior.unflat(theta)
    if noise is None:
        noise = torch.full_like(params.mass_scale, config.noise_floor)
    whitened = balance.residual(params, data, config, noise).reshape(-1)
    return torch.cat(
        [robust(whitened, config.outlier), (theta - prior.flat()) / prior.prior_sd(config)]
    )


def robust(z: Tensor, k: float) -> Tensor:
    """``sign(z) sqrt(ψ(z))`` for Huber's loss ψ with threshold k: z itself within ``|z| <= k``,
    ``sign(z) sqrt(2k|z| - k^2)`` beyond (continuous with its first derivative)."""
    beyond = torch.sqrt((2.0 * k * z.abs() - k * k).clamp_min(k * k))
    return torch.where(z.abs() <= k, z, torch.sign(z) * beyond)


def identify(
    balance: TorqueBalance,
    data: Transitions,
    config: IdentifyConfig,
    start: ArmParameters | None = None,
) -> ArmParameters:
    """The MAP θ by Levenberg-Marquardt (module docstring), solved again
    ``config.noise_rounds`` times with each joint's σ from its residuals. The step residual
    starts from the torque balance's estimate (solved once, each joint's σ the floor), whose
    residual is linear in the inertial parameters: from the prior, or from the midpoint form's
    estimate, its Gauss-Newton steps can stall in a local minimum with a negative payload
    (``tests/test_identify.py``). Where that start leads to an arm that cannot exist (a body of
    mass not above zero, :func:`physical`), the prior is the start instead; where that fails
    too, :class:`NumericalError`. Given ``start`` (the arm identified before, from earlier
    transitions of the same arm) the solution starts there instead of at the torque balance's
    estimate: from that estimate, a second identification of the Panda carrying 2 kg once found
    7.3 kg where the first had found 2.02 kg."""
    if data.q0.shape[0] == 0:
        raise LolgpsError("identification needs at least one transition")
    prior = ArmParameters.urdf(balance.dynamics)
    starts = [prior.flat()]
    if start is not None:
        starts.insert(0, start.flat())
    elif config.residual == "step":
        linear = replace(config, residual="torque")
        floor = torch.full_like(prior.mass_scale, linear.noise_floor)
        estimate = _solve(
            lambda t: objective(balance, prior, data, linear, t, floor), prior.flat(), config
        )
        starts.insert(0, estimate)
    for theta in starts:
        found = _from(balance, prior, data, config, theta)
        if physical(balance.dynamics, found):
            return found
    raise NumericalError(
        "the identified arm cannot exist (a body's mass is not above zero) from any start"
    )


def misfit(
    balance: TorqueBalance, params: ArmParameters, data: Transitions, config: IdentifyConfig
) -> float:
    """How badly the arm ``params`` explains the transitions: the sum of Huber's losses of the
    residuals (:func:`robust`), each joint's σ the residual's floor (the prior left out)."""
    noise = torch.full_like(params.mass_scale, config.noise_floor)
    whitened = balance.residual(params, data, config, noise)
    return float(robust(whitened, config.outlier).square().sum())


def identify_arm(
    balance: TorqueBalance,
    data: Transitions,
    config: IdentifyConfig,
    before: ArmParameters | None = None,
) -> ArmParameters | None:
    """θ identified from ``data`` (:func:`identify`, from ``before``, the arm identified last,
    if any) where it explains them no worse (:func:`misfit`) than the arm it would replace
    (``before``, or the URDF's); else None, with a warning saying why the model is kept (also
    where no arm that can exist fits them)."""
    try:
        params = identify(balance, data, config, before)
    except NumericalError as error:  # the model as it was: planned and fitted with as before
        warnings.warn(f"the arm could not be identified ({error}); its model is kept", stacklevel=3)
        return None
    kept = before or ArmParameters.urdf(balance.dynamics)
    if misfit(balance, params, data, config) > misfit(balance, kept, data, config):
        warnings.warn(
            "the identified arm explains the transitions worse than the model it would "
            "replace; that model is kept",
            stacklevel=3,
        )
        return None
    return params


def physical(dynamics: ArmDynamics, params: ArmParameters) -> bool:
    """Whether every body of the arm ``params`` makes of ``dynamics`` has a positive mass."""
    return bool((identified_dynamics(dynamics, params).body.mass > 0).all())


def _from(
    balance: TorqueBalance,
    prior: ArmParameters,
    data: Transitions,
    config: IdentifyConfig,
    theta: Tensor,
) -> ArmParameters:
    """:func:`identify`'s MAP θ from the start ``theta``."""
    noise = torch.full_like(prior.mass_scale, config.noise_floor)

    def solved(theta: Tensor, noise: Tensor) -> Tensor:
        theta = _solve(lambda t: objective(balance, prior, data, config, t, noise), theta, config)
        own = theta[-1]  # ρ, the last entry of ArmParameters.flat
        if 0.0 <= float(own) <= 1.0:
            return theta
        held = own.clamp(0.0, 1.0).reshape(1)
        rest = _solve(
            lambda t: objective(balance, prior, data, config, torch.cat([t, held]), noise),
            theta[:-1],
            config,
        )
        return torch.cat([rest, held])

    theta = solved(theta, noise)
    for _ in range(config.noise_rounds):
        whitened = balance.residual(prior.unflat(theta), data, config, noise)
        spread = (whitened * noise).abs().median(0).values * MAD_TO_SD
        scatter = spread.clamp_min(config.noise_floor)
        if torch.equal(scatter, noise):
            break
        noise = scatter
        theta = solved(theta, noise)
    return prior.unflat(theta)


def _solve(stacked: Callable[[Tensor], Tensor], theta: Tensor, config: IdentifyConfig) -> Tensor:
    """Levenberg-Marquardt on the stacked residuals ``stacked(θ)`` from ``theta``: Gauss-Newton
    steps ``(J^T J + λ diag(J^T J)) δ = -J^T R``, λ raised tenfold until a step lowers
    ``|R|^2`` and lowered tenfold after it; at most ``config.iterations`` steps, ending once
    one gains less than ``config.tolerance`` of the objective."""
    damping = 1e-3
    residual = stacked(theta)
    cost = float(residual.square().sum())
    for _ in range(config.iterations):
        J = torch.autograd.functional.jacobian(
            stacked, theta, vectorize=True, strategy="forward-mode"
        )
        H, g = J.T @ J, J.T @ residual
        scale = torch.diagonal(H).clamp_min(1e-12)
        while True:
            step = torch.linalg.solve(H + damping * torch.diag(scale), -g)
            trial = stacked(theta + step)
            trial_cost = float(trial.square().sum())
            if trial_cost <= cost or damping > 1e12:
                break
            damping *= 10.0
        if trial_cost > cost:
            break
        gain = (cost - trial_cost) / max(cost, 1e-300)
        theta, residual, cost = theta + step, trial, trial_cost
        damping = max(damping / 10.0, 1e-9)
        if gain < config.tolerance:
            break
    return theta
