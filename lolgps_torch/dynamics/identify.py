"""The arm's physical parameters identified from its rollouts, pulled toward its URDF.

The parameters θ (:class:`ArmParameters`) say how the arm differs from the URDF's rigid-body
model: body k's mass, first moment and rotational inertia scaled by ``s_k`` (a denser or
lighter link), a point payload of mass ``m_p`` at ``c_p`` in the last body's frame, viscous
damping ``Δb`` added to the URDF's, Coulomb friction ``F``, and the gravity compensation the
arm applies,

    ``c(q) = κ ((1 - ρ) g_0(q) + ρ g_θ(q))``

with g_0 the URDF's gravity torque and g_θ the identified arm's own (its scaled bodies and its
payload): a controller that compensates with the URDF's model has ρ = 0, one that compensates
the arm as it really is (its own model, or a counterbalance) ρ = 1, and κ scales either (κ = 1
compensates fully, 0 not at all). On the URDF's own arm g_θ = g_0 and ρ is not seen; a payload
or links that differ from the URDF tell the two apart: with ρ = 0 the payload sags under its
weight, with ρ = 1 it shows only through its inertia. ρ stays within [0, 1]: a fit that ends
outside is solved again with ρ held at the nearer end (free, the Panda's 1.5 kg compensated by
the URDF, its commands 50 ms late, came out as 0.73 kg with ρ = 1.79; held, 1.42 kg with ρ = 0).

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

import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Literal, NamedTuple, get_args

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.robot.rigid_body import ArmDynamics, BodyParameters
from lolgps_torch.state import StateLayout

Residual = Literal["torque", "speed", "step"]
MAD_TO_SD = 1.4826  # σ of zero-mean Gaussian noise per median of its absolute value


@dataclass(frozen=True)
class IdentifyConfig:
    """The identification's noise model, prior and solver.

    :param torque_noise: σ_τ, the standard deviation of the torque residual (N m), and the
        least any joint's is taken to be.
    :param residual: torque, the balance ``r``; speed, the joint-speed change it leaves over
        the control step at the midpoint, ``r_v``; or step, the control step integrated as the
        simulator does, ``r_s`` (module docstring).
    :param speed_noise: the speed and step residuals' σ (rad/s), and the least any joint's is
        taken to be.
    :param noise_rounds: times the MAP estimate is solved again with each joint's σ_j the
        robust scale of its residuals at the last solution, ``1.4826 median |r_j|`` (floored at
        the residual's σ, :attr:`noise_floor`), so that noisy observations weigh no more
        against the prior than their scatter says (0: that σ for every joint throughout).
    :param outlier: k, the whitened residual beyond which Huber's loss grows linearly (module
        docstring).
    :param scale_sd: prior standard deviation of each body's scale s_k.
    :param payload_sd: prior standard deviation of the payload's mass (kg).
    :param payload_com_sd: prior standard deviation of the payload's position (m).
    :param damping_sd: prior standard deviation of the added damping (N m s/rad).
    :param friction_sd: prior standard deviation of the Coulomb friction (N m).
    :param compensation_sd: prior standard deviation of κ.
    :param own_sd: prior standard deviation of ρ, the compensation's share that is the arm's
        own gravity (centred on 1/2).
    :param friction_speed: v_F, the joint speed (rad/s) over which the friction's sign is
        smoothed.
    :param iterations: at most this many Levenberg-Marquardt steps.
    :param tolerance: stop once a step changes the objective by less than this fraction.
    """

    torque_noise: float = 0.5
    noise_rounds: int = 1
    outlier: float = 3.0
    residual: Residual = "step"
    speed_noise: float = 0.01
    scale_sd: float = 0.3
    payload_sd: float = 2.0
    payload_com_sd: float = 0.1
    damping_sd: float = 1.0
    friction_sd: float = 1.0
    compensation_sd: float = 0.02
    own_sd: float = 0.5
    friction_speed: float = 0.01
    iterations: int = 30
    tolerance: float = 1e-9

    @property
    def noise_floor(self) -> float:
        """The residual's σ: ``speed_noise`` (rad/s) or ``torque_noise`` (N m)."""
        return self.torque_noise if self.residual == "torque" else self.speed_noise

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "noise_rounds":
                if value < 0:
                    raise LolgpsError(f"identification noise_rounds must be >= 0, got {value}")
            elif f.name == "residual":
                if value not in get_args(Residual):
                    raise LolgpsError(
                        f"identification residual {value!r}: one of {get_args(Residual)}"
                    )
            elif not (math.isfinite(value) and value > 0):
                raise LolgpsError(f"identification {f.name} must be positive, got {value}")


@dataclass(frozen=True)
class ArmParameters:
    """θ: how the arm differs from its URDF (module docstring).

    :param mass_scale: s ``[n]``. :param payload: m_p ``[]`` (kg).
    :param payload_com: c_p ``[3]`` in the last body's frame (m).
    :param damping: Δb ``[n]``. :param friction: F ``[n]``.
    :param compensation: κ ``[]``. :param own: ρ ``[]``.
    """

    mass_scale: Tensor
    payload: Tensor
    payload_com: Tensor
    damping: Tensor
    friction: Tensor
    compensation: Tensor
    own: Tensor

    @staticmethod
    def urdf(dynamics: ArmDynamics) -> ArmParameters:
        """The prior's centre: the URDF's arm, compensated fully (κ = 1, ρ = 1/2), a payload
        of 0 at the peg tip."""
        n, like = dynamics.n, dynamics.body.mass
        q = like.new_zeros(n)
        frames = dynamics.frames(q)
        tip = dynamics.points(frames)[0]
        tip_in_last = frames.R[-1].T @ (tip - frames.p[-1])
        zeros = like.new_zeros(n)
        one = like.new_ones(())
        return ArmParameters(
            like.new_ones(n), like.new_zeros(()), tip_in_last, zeros, zeros, one, one / 2
        )

    def flat(self) -> Tensor:
        """θ as one vector ``[3n + 6]`` in field order."""
        return torch.cat([getattr(self, f.name).reshape(-1) for f in fields(self)])

    def unflat(self, theta: Tensor) -> ArmParameters:
        """Parameters shaped as these from the vector ``theta`` (:meth:`flat`'s inverse)."""
        parts, start = {}, 0
        for f in fields(self):
            like = getattr(self, f.name)
            parts[f.name] = theta[start : start + like.numel()].reshape(like.shape)
            start += like.numel()
        return ArmParameters(**parts)

    def prior_sd(self, config: IdentifyConfig) -> Tensor:
        """The prior's standard deviation per entry of :meth:`flat`."""
        sd = {
            "mass_scale": config.scale_sd,
            "payload": config.payload_sd,
            "payload_com": config.payload_com_sd,
            "damping": config.damping_sd,
            "friction": config.friction_sd,
            "compensation": config.compensation_sd,
            "own": config.own_sd,
        }
        return torch.cat(
            [torch.full_like(getattr(self, f.name).reshape(-1), sd[f.name]) for f in fields(self)]
        )


class Transitions(NamedTuple):
    """Observed control steps: start angles and velocities ``[B, n]``, the commands
    ``[B, h+1, n]`` (the transition's own u_t, then the h past actions the state carries,
    newest first: ``u_{t-1}, ..., u_{t-h}``; h = 0 without a known delay), end angles and
    velocities ``[B, n]``."""

    q0: Tensor
    qd0: Tensor
    commands: Tensor
    q1: Tensor
    qd1: Tensor

    @property
    def u(self) -> Tensor:
        """The transitions' own commands u_t ``[B, n]``."""
        return self.commands[:, 0]

    @staticmethod
    def from_rollouts(x: Tensor, u: Tensor, layout: StateLayout, keep: Tensor) -> Transitions:
        """The transitions of rollouts ``x: [N, T+1, dX]`` (the final state included),
        ``u: [N, T, dU]`` where ``keep: [N, T]`` (e.g. free of contact); the past commands
        from the start states' action history (:attr:`StateLayout.actions`)."""
        start, end = x[:, :-1][keep], x[:, 1:][keep]
        past = start[:, layout.actions].unflatten(-1, (layout.history, layout.dU))
        commands = torch.cat([u[keep][:, None], past], 1)
        return Transitions(
            start[:, layout.q], start[:, layout.qd], commands, end[:, layout.q], end[:, layout.qd]
        )


def identified_dynamics(dynamics: ArmDynamics, params: ArmParameters) -> ArmDynamics:
    """``dynamics`` with θ's bodies and damping: body k's inertial parameters times s_k, the
    payload's mass m_p, first moment ``m_p c_p`` and inertia ``m_p (|c_p|^2 1 - c_p c_p^T)``
    added to the last body."""
    body, s = dynamics.body, params.mass_scale
    last = torch.zeros_like(s)
    last[-1] = 1.0
    m, c = params.payload, params.payload_com
    point = m * (c.dot(c) * torch.eye(3, dtype=c.dtype, device=c.device) - torch.outer(c, c))
    scaled = BodyParameters(
        mass=s * body.mass + last * m,
        first_moment=s[:, None] * body.first_moment + last[:, None] * (m * c),
        inertia=s[:, None, None] * body.inertia + last[:, None, None] * point,
        link_body=body.link_body,
        link_mass=s[body.link_body] * body.link_mass,
        link_com=body.link_com,
        link_inertia=s[body.link_body, None, None] * body.link_inertia,
    )
    return dynamics.with_parameters(scaled, dynamics.joint_damping + params.damping)


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
