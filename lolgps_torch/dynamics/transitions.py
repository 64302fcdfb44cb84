"""The arm's transitions that identification (:mod:`lolgps_torch.dynamics.identify`) fits: the
control steps of its rollouts that are free of contact and of the joint limits, the newest
:data:`IDENTIFY_TRANSITIONS` of them kept (:class:`TransitionStore`)."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.state import StateLayout
from lolgps_torch.types import Trajectories

IDENTIFY_TRANSITIONS = 400  # the newest free-space transitions identification uses
CLEARANCE = 0.02  # m: a tip this far above the table touches nothing
LIMIT_MARGIN = 0.05  # rad (or m): a joint this far from its limits is free


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


def free_transitions(
    samples: Trajectories, arm: ArmSpec, layout: StateLayout, depth: float, dt: float
) -> tuple[Tensor, Tensor]:
    """The states ``[N, T+1, dX]`` of ``samples`` (the final one appended) and which of their
    transitions ``[N, T]`` are free of contact (before and after, the tip higher than the
    table, ``depth`` below the hole's mouth, by :data:`CLEARANCE` and the peg pointing down, its
    top above its tip, so that no part of it is lower than the tip by more than its radius)
    and of the joint limits: each joint farther from them, at both ends, than
    :data:`LIMIT_MARGIN` and the way it can go in one control step ``dt`` at the larger of its
    two speeds, ``margin + dt max(|qd_0|, |qd_1|)`` (a joint 0.08 rad short of its limit at
    17 rad/s strikes it within the step and may be back inside at its end, moving away)."""
    lower, upper = (
        torch.tensor(limit, dtype=torch.float64, device=samples.x.device)
        for limit in (arm.lower, arm.upper)
    )
    x = torch.cat([samples.x, samples.final_state[:, None]], 1)
    q, qd, points = x[..., layout.q], x[..., layout.qd], x[..., layout.points]
    tip_height = points[..., 2]
    # the points are offsets from targets, the top's above the tip's by the separation
    top_over_tip = points[..., 5] - tip_height - arm.point_offsets[1][2]
    clear = (tip_height > depth + CLEARANCE) & (top_over_tip > 0.0)
    room = torch.minimum(q - lower, upper - q)
    reach = LIMIT_MARGIN + dt * torch.maximum(qd[:, :-1].abs(), qd[:, 1:].abs())
    within = ((room[:, :-1] > reach) & (room[:, 1:] > reach)).all(-1)
    return x, clear[:, :-1] & clear[:, 1:] & within


class TransitionStore:
    """The newest ``keep`` free transitions (:func:`free_transitions`) of the rollouts
    recorded on one arm: ``arm`` with the state ``layout``, the hole ``depth`` (m) deep and
    the control step ``dt`` (s)."""

    def __init__(
        self,
        arm: ArmSpec,
        layout: StateLayout,
        depth: float,
        dt: float,
        keep: int = IDENTIFY_TRANSITIONS,
    ) -> None:
        self.arm, self.layout, self.depth, self.dt, self.keep = arm, layout, depth, dt, keep
        #: the transitions kept, oldest first (None before any rollout is recorded)
        self.kept: Transitions | None = None

    def free(self, samples: Trajectories) -> tuple[Tensor, Tensor]:
        """:func:`free_transitions` of ``samples`` on this arm."""
        return free_transitions(samples, self.arm, self.layout, self.depth, self.dt)

    def record(self, samples: Trajectories) -> None:
        """Keep the free transitions of ``samples``, the newest ``keep`` of all recorded."""
        x, free = self.free(samples)
        new = Transitions.from_rollouts(x, samples.u, self.layout, free)
        parts = (new,) if self.kept is None else (self.kept, new)
        self.kept = Transitions(
            *(torch.cat(part)[-self.keep :] for part in zip(*parts, strict=True))
        )

    @property
    def data(self) -> Transitions | None:
        """The transitions kept; None while there are none."""
        return None if self.kept is None or self.kept.q0.shape[0] == 0 else self.kept
