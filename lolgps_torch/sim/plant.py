"""The simulated arm as it really is: how the plant departs from the URDF the learner is given.

The learner's model of the arm (its dynamics prior, the planned start, the point features)
is built from the URDF alone; these settings change only the PyBullet body and what the world
does with it, so the learner never reads them. With the defaults the plant is the URDF.

- Inertia: link i's mass and principal inertias are multiplied by ``f_i ~ U[1 - S, 1 + S]``,
  drawn from ``seed`` (a uniformly denser or lighter link; its centre of mass stays put).
- Payload: ``m_p`` kg added to the peg link at its centre of mass.
- Gravity compensation ``g(q)`` added to the command (``tau = clip(u + g(q), ±effort)``):
  inverse dynamics at zero velocity and acceleration of the simulated body (``plant``), of
  the URDF as the learner is given it (``model``), or none (``g = 0``).
- Joint friction: a Coulomb torque of at most ``F`` opposing each joint's motion (PyBullet's
  velocity motor at target speed zero with maximum force ``F``).
- Sensor noise: the observed joint angles are ``q + e_q``, ``e_q ~ N(0, s^2)``, and the
  velocities ``qd + e_qd``, ``e_qd ~ N(0, (10 s)^2)``; the point features stay exact.
- Latency: the command issued at time t acts from ``t + d`` on, ``d`` a whole number of
  physics steps (``dt / substeps``); before the first command acts the arm gets ``u = 0``.
- Limits: as a real arm's controller does, the world stops the arm where a joint passes its
  velocity limit or comes near a position limit, and the rollout ends as a fault
  (:class:`~lolgps_torch.sim.reflex.Reflex`); ``off``: the arm moves on past them.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import INERTIA_KEYS

GravityCompensation = Literal["plant", "model", "none"]
Limits = Literal["reflex", "off"]

VELOCITY_NOISE_RATIO = 10.0  # velocity noise per unit of joint-angle noise (rad/s per rad)


@dataclass(frozen=True)
class PlantConfig:
    """How the simulated arm differs from its URDF (module docstring).

    :param inertia_scale: S: each link's mass and inertia scaled by a factor uniform in
        [1-S, 1+S] (0 <= S < 1).
    :param seed: seed of the per-link inertia factors and of the sensor noise.
    :param payload: mass (kg) added to the peg link, unknown to the learner.
    :param gravity_compensation: gravity-compensation torque computed from the simulated
        body (plant), from the URDF the learner is given (model), or none.
    :param joint_friction: Coulomb friction torque (N m) at every joint.
    :param obs_noise: standard deviation (rad) of the noise on the observed joint angles; the
        joint velocities get 10 times as much (rad/s).
    :param action_delay: seconds between a command and the moment it acts on the arm, any
        duration: over a physics step that a delay of k + f physics steps splits, the arm
        feels the command f of the step longer (:meth:`delay_steps`).
    :param limits: reflex: a joint past its velocity limit or near a position limit stops
        the arm and ends the rollout as a fault, as a real arm's controller does; off: no limit
        is watched.
    """

    inertia_scale: float = 0.0
    seed: int = 0
    payload: float = 0.0
    gravity_compensation: GravityCompensation = "plant"
    joint_friction: float = 0.0
    obs_noise: float = 0.0
    action_delay: float = 0.0
    limits: Limits = "reflex"

    def __post_init__(self) -> None:
        if self.limits not in ("reflex", "off"):
            raise LolgpsError(f"--limits must be reflex or off, got {self.limits!r}")
        if not (math.isfinite(self.inertia_scale) and 0.0 <= self.inertia_scale < 1.0):
            raise LolgpsError(f"--plant-inertia-scale must be in [0, 1), got {self.inertia_scale}")
        if self.seed < 0:
            raise LolgpsError(f"--plant-seed must be >= 0, got {self.seed}")
        if self.gravity_compensation not in ("plant", "model", "none"):
            raise LolgpsError(
                "--gravity-compensation must be plant, model or none, got "
                f"{self.gravity_compensation!r}"
            )
        for flag, value in (
            ("--payload", self.payload),
            ("--joint-friction", self.joint_friction),
            ("--obs-noise", self.obs_noise),
            ("--action-delay", self.action_delay),
        ):
            if not (math.isfinite(value) and value >= 0.0):
                raise LolgpsError(f"{flag} must be >= 0 and finite, got {value}")

    @property
    def reshaped(self) -> bool:
        """Whether the simulated body's masses or inertias differ from the URDF's."""
        return self.inertia_scale > 0.0 or self.payload > 0.0

    def delay_steps(self, physics_step: float) -> tuple[int, float]:
        """The delay as ``k`` whole physics steps of ``physics_step`` seconds and a fraction
        ``f`` in [0, 1) of the next, ``d = (k + f) h``. The torque acting over physics step s
        is then the mean over that step of the commands shifted by d (each held for a physics
        step): ``(1 - f) u_{s-k} + f u_{s-k-1}``."""
        steps = self.action_delay / physics_step
        if abs(steps - round(steps)) < 1e-9:  # whole steps, to rounding
            return round(steps), 0.0
        return math.floor(steps), steps - math.floor(steps)

    def link_factors(self, links: int) -> np.ndarray:
        """The per-link mass and inertia factors ``[links]`` (all 1 when S = 0)."""
        if self.inertia_scale == 0.0:
            return np.ones(links)
        rng = np.random.default_rng(self.seed)
        return rng.uniform(1.0 - self.inertia_scale, 1.0 + self.inertia_scale, links)

    def noise(self, key: tuple[int, ...]) -> np.random.Generator | None:
        """The sensor-noise generator of the rollout ``key`` (None without noise): a rollout's
        noise depends on the plant's seed and its key alone."""
        if self.obs_noise == 0.0:
            return None
        return np.random.default_rng((self.seed, *key))


NOMINAL_PLANT = PlantConfig()  # the arm exactly as its URDF describes it


def believed_plant(compensating: bool, delay: float, limits: Limits) -> PlantConfig:
    """The arm as a learner believes it is: as its description has it, without gravity
    compensation of its own where the learner adds it (``compensating``, after the probe found
    none), acting ``delay`` s late (the delay it allows for), with the arm's ``limits``, and
    none of what the learner is not told (a payload, friction, other inertia, sensor noise)."""
    return PlantConfig(
        gravity_compensation="none" if compensating else "plant", action_delay=delay, limits=limits
    )


def reshaped_urdf(text: str, factors: Mapping[str, float], added: Mapping[str, float]) -> str:
    """The URDF ``text`` with link ``name``'s mass and inertia tensor times ``factors[name]``
    and ``added[name]`` kg more mass at its centre of mass (links not named: unchanged)."""
    root = ET.fromstring(text)
    for link in root.iter("link"):
        name, inertial = link.get("name", ""), link.find("inertial")
        if inertial is None or (name not in factors and name not in added):
            continue
        f = factors.get(name, 1.0)
        mass, inertia = inertial.find("mass"), inertial.find("inertia")
        if mass is not None:
            mass.set("value", repr(f * float(mass.get("value", "0")) + added.get(name, 0.0)))
        if inertia is not None:
            for key in INERTIA_KEYS:
                inertia.set(key, repr(f * float(inertia.get(key, "0"))))
    return ET.tostring(root, encoding="unicode")
