"""The reflex of a real arm's controller, which the simulated arm has too with ``--limits
reflex`` (:class:`~lolgps_torch.sim.plant.PlantConfig`): a joint too fast, or too near a
position limit, stops the arm."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lolgps_torch.robot.spec import ArmSpec

POSITION_MARGIN = 0.02  # rad: a joint this near a position limit trips the reflex


class Reflex(NamedTuple):
    """The limits a real arm's controller watches (``[dof]`` each): a joint faster than its
    velocity limit ``|q-dot_j| > v_j``, or nearer than :data:`POSITION_MARGIN` to a position
    limit of a bounded joint, ``q_j < lower_j + margin`` or ``q_j > upper_j - margin``, stops
    the arm (docs/RELIABILITY.md, "The arm's limits")."""

    velocity: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def of(cls, arm: ArmSpec) -> Reflex:
        """The reflex of ``arm``'s URDF limits (a continuous joint has no position limit)."""
        bounded = np.asarray(arm.bounded, dtype=bool)
        lower = np.where(bounded, np.asarray(arm.lower) + POSITION_MARGIN, -np.inf)
        upper = np.where(bounded, np.asarray(arm.upper) - POSITION_MARGIN, np.inf)
        return cls(np.asarray(arm.velocity, dtype=np.float64), lower, upper)

    def violation(self, q: np.ndarray, qd: np.ndarray, step: int) -> str | None:
        """The first limit the joint state ``(q, qd)`` passes, as one line naming the joint
        (from 1) and the control ``step``; None within every limit."""
        over = np.abs(qd) / self.velocity
        j = int(np.argmax(over))
        if over[j] > 1.0:
            return (
                f"joint {j + 1} at {abs(qd[j]):.3g} rad/s over its velocity limit "
                f"{self.velocity[j]:.3g} at step {step}"
            )
        outside = (q < self.lower) | (q > self.upper)
        if outside.any():
            j = int(np.argmax(outside))
            return (
                f"joint {j + 1} at {q[j]:.3g} rad, within {POSITION_MARGIN} rad of its position "
                f"limits [{self.lower[j] - POSITION_MARGIN:.3g}, "
                f"{self.upper[j] + POSITION_MARGIN:.3g}] at step {step}"
            )
        return None
