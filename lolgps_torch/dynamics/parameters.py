"""The arm's physical parameters θ, which identification (:mod:`lolgps_torch.dynamics.identify`)
estimates from its transitions, their prior, the arm they make of the URDF's, and the
identification's settings.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Literal, get_args

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.rigid_body import ArmDynamics, BodyParameters

Residual = Literal["torque", "speed", "step"]


@dataclass(frozen=True)
class IdentifyConfig:
    """The identification's noise model, prior and solver.

    :param torque_noise: σ_τ, the standard deviation of the torque residual (N m), and the
        least any joint's is taken to be.
    :param residual: torque, the balance ``r``; speed, the joint-speed change it leaves over
        the control step at the midpoint, ``r_v``; or step, the control step integrated as the
        simulator does, ``r_s`` (:mod:`lolgps_torch.dynamics.identify`).
    :param speed_noise: the speed and step residuals' σ (rad/s), and the least any joint's is
        taken to be.
    :param noise_rounds: times the MAP estimate is solved again with each joint's σ_j the
        robust scale of its residuals at the last solution, ``1.4826 median |r_j|`` (floored at
        the residual's σ, :attr:`noise_floor`), so that noisy observations weigh no more
        against the prior than their scatter says (0: that σ for every joint throughout).
    :param outlier: k, the whitened residual beyond which Huber's loss grows linearly
        (:mod:`lolgps_torch.dynamics.identify`).
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
