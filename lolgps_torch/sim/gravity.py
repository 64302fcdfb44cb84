"""Whether the arm's torque commands are compensated for gravity, found from how it moves when
let go (no plant setting read).

Probe: ``rollouts`` rollouts of ``steps`` control steps from rest at the start pose q0, every
command zero. The learner's own model of the arm (the URDF's rigid-body dynamics,
:class:`~lolgps_torch.sim.model.ControlStep`) predicts each observed step under two hypotheses:
the arm adds ``kappa g(q)`` to every command, with ``kappa = 1`` (compensated: the arm stays
at rest) or ``kappa = 0`` (not: it falls). To first order in dt,

    qd_{t+1} - qd_t = -(1 - kappa) dt M(q_t)^{-1} g(q_t)

(M and g the URDF's mass matrix and gravity torque; the model also carries the joint and link
damping and the physics substeps). Each hypothesis leaves the residual

    RSS(kappa) = sum_t sum_j (I_j (qd_{t+1,j} - f_kappa(x_t, 0)_j) / dt)^2

(``I_j`` joint j's effective inertia at q0 in the URDF's arm: the residual in N m). The
compensation is missing where ``RSS(0)`` is :data:`MARGIN` times smaller than ``RSS(1)``,
present where ``RSS(1)`` is; otherwise (an arm that barely moves under gravity at q0, or one
compensated in part) the probe is inconclusive and the arm is taken as compensated.
Commands of zero leave any command delay without effect. A rollout the arm's controller stops
(a joint past its velocity limit: an arm that falls fast) gives the steps before it alone; an
arm stopped within the first step of every rollout fell faster than any joint may move, and is
taken as not compensated.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.model import ControlStep
from lolgps_torch.sim.simulator import World, WorldConfig

# how many times smaller one hypothesis' residual must be than the other's to decide: on the
# KUKA and pybullet_data's Panda the hypothesis that holds leaves 1e-18 N^2 m^2 against the
# other's 450-620; with 1 mrad of sensor noise 0.9-1.6 against 450-630; a payload of 1 kg
# the arm's own (URDF) compensation leaves out, RSS(1) 13-15 against 320-450 (21-33 times)
MARGIN = 4.0


@dataclass(frozen=True)
class GravityConfig:
    """Settings of the gravity-compensation probe (module docstring).

    :param rollouts: rollouts from rest at the start pose (each with its own sensor noise).
    :param steps: control steps of zero command per rollout.
    """

    rollouts: int = 2
    steps: int = 2

    def __post_init__(self) -> None:
        if self.rollouts < 1 or self.steps < 1:
            raise LolgpsError(
                f"gravity probe: rollouts >= 1 and steps >= 1 needed, got {self.rollouts}, "
                f"{self.steps}"
            )


class GravityEstimate(NamedTuple):
    """The probe's verdict: ``compensated`` (also when not ``conclusive``), and the residuals
    ``RSS(0)`` (no compensation) and ``RSS(1)`` (compensated), N^2 m^2."""

    compensated: bool
    conclusive: bool
    rss_none: float
    rss_compensated: float


def let_go(world: World, q0: np.ndarray, config: GravityConfig) -> tuple[np.ndarray, np.ndarray]:
    """The observed transitions of the probe's rollouts (module docstring) in ``world``, which
    must have its hole set: the states before and after each step, ``([K, dX], [K, dX])``,
    each rollout's up to the step in which the arm's controller stopped it, if any."""
    zero = np.zeros(world.arm.dof)
    before, after = [], []
    for r in range(config.rollouts):
        x = world.reset(q0, key=(r,))
        for _ in range(config.steps):
            nxt = world.step(zero)
            if world.fault is not None:
                break
            before.append(x)
            after.append(nxt)
            x = nxt
    width = len(world.reset(q0))
    return np.reshape(before, (-1, width)), np.reshape(after, (-1, width))


def estimate_gravity(
    moves: tuple[np.ndarray, np.ndarray], arm: ArmSpec, config: WorldConfig, inertia: np.ndarray
) -> GravityEstimate:
    """The verdict of the module docstring on the transitions ``moves`` of :func:`let_go` in
    a world of ``config`` with ``arm``, from the learner's model of the arm and the joints'
    effective inertias ``inertia: [n]``."""
    if len(moves[0]) == 0:  # stopped within its first step, every time: it falls fast
        return GravityEstimate(False, True, 0.0, float("inf"))
    compensated = ControlStep(arm, config)
    falling = ControlStep(arm, config, identified=(compensated.urdf, 0.0, 0.0))
    before, after = (torch.from_numpy(states) for states in moves)
    u = torch.zeros(*before.shape[:-1], arm.dof, dtype=torch.float64)
    qd = compensated.layout.qd
    scale = torch.as_tensor(inertia, dtype=torch.float64) / config.dt
    rss_none, rss_compensated = (
        float((((after[..., qd] - model(before, u)[..., qd]) * scale) ** 2).sum())
        for model in (falling, compensated)
    )
    if rss_none * MARGIN < rss_compensated:
        return GravityEstimate(False, True, rss_none, rss_compensated)
    conclusive = rss_compensated * MARGIN < rss_none
    return GravityEstimate(True, conclusive, rss_none, rss_compensated)
