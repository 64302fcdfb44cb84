"""The state vector x of docs/ALGORITHM.md section 1, described once by names and slices.

For an arm with n actuated joints (dX = 2n + 12 + hn, dU = n)::

    x = [ q (n) | q_dot (n) | p_tip - p*_tip (3) | p_top - p*_top (3) | v_tip (3) | v_top (3)
          | u_{t-1} (n) | ... | u_{t-h} (n) ]

The point velocities are finite differences of the point offsets over the control step dt.
The last h actions (none by default) make the state Markov for an arm whose commands act
late: a command still pending at t is part of what decides x_{t+1}.
Nothing downstream indexes the state with literal numbers: use these slices.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StateLayout:
    """Names and slices of the state vector for an arm with ``n_joints`` actuated joints and
    the last ``history`` actions in the state."""

    n_joints: int
    history: int = 0

    @property
    def dX(self) -> int:
        return 2 * self.n_joints + 12 + self.history * self.n_joints

    @property
    def dU(self) -> int:
        return self.n_joints

    @property
    def q(self) -> slice:
        return slice(0, self.n_joints)

    @property
    def qd(self) -> slice:
        return slice(self.n_joints, 2 * self.n_joints)

    @property
    def points(self) -> slice:
        """Both end-effector points minus their targets, tip then top, ``[6]``."""
        return slice(2 * self.n_joints, 2 * self.n_joints + 6)

    @property
    def point_velocities(self) -> slice:
        return slice(2 * self.n_joints + 6, 2 * self.n_joints + 12)

    @property
    def actions(self) -> slice:
        """The last ``history`` actions, newest first, ``[history * n]``."""
        return slice(2 * self.n_joints + 12, self.dX)

    def names(self) -> list[str]:
        """One name per state entry, e.g. ``q0``, ``qd0``, ``tip_x``, ``top_vz``, ``u1_0``
        (joint 0's action one step back)."""
        n = self.n_joints
        pts = [f"{p}_{a}" for p in ("tip", "top") for a in "xyz"]
        vel = [f"{p}_v{a}" for p in ("tip", "top") for a in "xyz"]
        past = [f"u{k}_{i}" for k in range(1, self.history + 1) for i in range(n)]
        return [f"q{i}" for i in range(n)] + [f"qd{i}" for i in range(n)] + pts + vel + past

    def as_dict(self) -> dict[str, list[int]]:
        """``{name: [start, stop]}`` for each block, for metadata files."""
        blocks = {
            "q": self.q,
            "qd": self.qd,
            "points": self.points,
            "point_velocities": self.point_velocities,
        }
        if self.history:
            blocks["actions"] = self.actions
        return {k: [s.start, s.stop] for k, s in blocks.items()}
