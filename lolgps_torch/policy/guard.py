"""The global policy's guard: bounds learnt from D_g, and braking where the policy leaves them.

Away from its data a ReLU policy extrapolates, and with a gain head it can ask for hundreds of
times the largest torque its teachers ever gave, flinging the arm a metre or more. The guard
keeps the policy inside what its teachers did, with bounds fitted to every condition's D_g:

    u_t = clip(mu_theta(x_t) (+ noise), -tau, tau)      tau_j = torque_margin max |mu_cur,j|
    once |q-dot_j| > v_j for some joint (v_j = speed_margin max |q-dot_j| over D_g), and for
    the rest of the rollout:  u_t = clip(-beta B^-1 q-dot_t, -tau, tau)

(tau_j infinite unless a torque margin is given: the bound cost reaches to far holes and kept
the brake from stopping a flung arm).

with ``B`` the arm's response to a torque over one control step fitted to D_g's transitions by
least squares, ``q-dot_{t+1} - q-dot_t ~ B u_t + c``: the brake takes ``beta`` of the joint
speeds away per control step (the arm's inertia, coupling included, from the data, with no
model), so the arm stops where it left the speeds its teachers used.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError


class Guard(NamedTuple):
    """Torque bounds ``tau [dU]``, the speeds ``v [dU]`` that trip the brake and the brake's
    gain ``-beta B^-1``, ``[dU, dU]`` (module docstring)."""

    torque: Tensor
    speed: Tensor
    brake: Tensor

    @classmethod
    def off(cls, dU: int, device: torch.device | str = "cpu") -> Guard:
        """A guard that never acts: unbounded torques and speeds."""
        inf = torch.full((dU,), float("inf"), dtype=torch.float64, device=device)
        return cls(inf, inf.clone(), torch.zeros(dU, dU, dtype=torch.float64, device=device))


def fit_guard(
    x: Tensor,
    u: Tensor,
    mean_cur: Tensor,
    qd: slice,
    torque_margin: float | None,
    speed_margin: float,
    beta: float,
) -> Guard:
    """The guard of rollouts with states ``x: [M, T+1, dX]`` (``x_T`` the state after the last
    action), actions ``u: [M, T, dU]`` and teacher means ``mean_cur: [M, T, dU]``; ``qd`` is
    the state's joint-speed slice (M >= 1); ``torque_margin`` None leaves torques unbounded."""
    if x.shape[0] == 0:
        raise LolgpsError("the policy's guard needs at least one rollout")
    speeds = x[..., qd]  # [M, T+1, n]
    change = (speeds[:, 1:] - speeds[:, :-1]).flatten(0, 1)  # [M T, n]
    actions = u.flatten(0, 1)
    design = torch.cat([actions, torch.ones_like(actions[:, :1])], dim=1)  # [M T, dU + 1]
    # least squares by the normal equations, a (dU + 1)-sized solve: the same bits in every
    # process (LAPACK's least-squares and SVD drivers are not)
    solution = torch.linalg.solve(design.T @ design, design.T @ change)  # [dU + 1, n]
    B = solution[:-1].T  # [n, dU]
    largest = mean_cur.abs().flatten(0, 1).amax(0)
    torque = (
        torch.full_like(largest, math.inf) if torque_margin is None else torque_margin * largest
    )
    speed = speed_margin * speeds.abs().flatten(0, 1).amax(0)
    return Guard(torque, speed, -beta * torch.linalg.inv(B))


def guarded(
    u: Tensor,
    qd: Tensor,
    guard: Guard,
    tripped: Tensor,
    product: Callable[[Tensor, Tensor], Tensor] = lambda x, A: x @ A.T,
) -> tuple[Tensor, Tensor]:
    """Actions ``u: [n, dU]`` at joint speeds ``qd: [n, dU]`` through the guard, given which
    rollouts had ``tripped`` it before (``[n]`` bool); returns the actions and the new
    ``tripped``. ``product(x, A)`` is ``x @ A^T`` (a row-wise form of it for lockstep
    rollouts)."""
    tripped = tripped | (qd.abs() > guard.speed).any(-1)
    held = torch.where(tripped[:, None], product(qd, guard.brake), u)
    return torch.maximum(torch.minimum(held, guard.torque), -guard.torque), tripped
