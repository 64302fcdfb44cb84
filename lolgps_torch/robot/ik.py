"""Inverse kinematics of the two peg points, in batches: where an arm can put its peg.

A pose is fixed by the two peg points ``p(q) = (p_tip, p_top)``.  Inverse kinematics solves
``min_q |p(q) - p*|^2`` by damped least squares (Levenberg-Marquardt steps
``dq = (J^T J + mu I)^{-1} (J^T e + 0.1 mu (q_mid - q) / span)``, whose last term drifts the
redundant directions towards mid-range) from several starts in one batch, and keeps the
converged solution furthest inside the joint limits (:func:`solve_ik_batch`).
:func:`follow` tracks a straight line of targets from a pose as a controller would, and
:func:`dexterity` measures how near a pose is to a singular one.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.spec import ArmSpec

_PATH_STEPS = 10  # way points of follow's straight line
_PATH_ITERATIONS = 20  # damped least-squares steps at most per way point
_MU = 1e-4  # damping of the least-squares steps


def _damped_step(
    q: Tensor, J: Tensor, e: Tensor, bounds: tuple[Tensor, Tensor], drift: Tensor | None = None
) -> Tensor:
    """One damped least-squares step towards point errors ``e [B, 6]`` with Jacobians
    ``J [B, 6, n]``: ``dq = (J^T J + mu I)^{-1} (J^T e + drift)``, shortened to at most 0.2 rad
    (a trust region), the new pose clamped to ``bounds``."""
    eye = torch.eye(q.shape[-1], dtype=q.dtype, device=q.device)
    rhs = (J.transpose(-1, -2) @ e[..., None])[..., 0]
    dq = torch.linalg.solve(
        J.transpose(-1, -2) @ J + _MU * eye, rhs if drift is None else rhs + drift
    )
    dq = dq * (0.2 / dq.norm(dim=-1, keepdim=True).clamp(min=0.2))
    return (q + dq).clamp(*bounds)


def solve_ik(
    kin: PegKinematics, arm: ArmSpec, targets: Tensor, margin: float, iterations: int = 200
) -> tuple[Tensor, Tensor]:
    """Best IK solution for point targets ``[2, 3]``: returns ``(q [n], point error in m)``."""
    q, err = solve_ik_batch(kin, arm, targets[None], margin, iterations)
    return q[0], err[0]


def solve_ik_batch(
    kin: PegKinematics,
    arm: ArmSpec,
    targets: Tensor,
    margin: float,
    iterations: int = 200,
    starts: int = 16,
    seeds: Tensor | None = None,
    group: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Best IK solutions for ``K`` point targets ``[K, 2, 3]``, each from ``starts`` starts
    (the first at mid-range, the second at ``seeds[k]`` if given, the others random): returns
    ``(q [K, n], point error [K] in m)``.  It stops once every target is solved or, with
    ``group``, once every target of some run of ``group`` consecutive ones is."""
    K, n = targets.shape[0], arm.dof
    lo = torch.tensor(arm.lower, dtype=torch.float64, device=kin.device)
    hi = torch.tensor(arm.upper, dtype=torch.float64, device=kin.device)
    span, mid = hi - lo, (hi + lo) / 2
    gen = torch.Generator().manual_seed(0)
    u = torch.rand(starts, n, generator=gen, dtype=torch.float64).to(kin.device)
    q = (lo + span * (0.2 + 0.6 * u)).repeat(K, 1)  # [K * S, n], target-major
    q[::starts] = mid
    if seeds is not None:
        q[1::starts] = seeds.clamp(lo + margin * span, hi - margin * span)
    goal = targets.reshape(K, 1, 6).expand(K, starts, 6).reshape(K * starts, 6)
    for _ in range(iterations):
        pts, J = kin.points_and_jacobian(q)
        e = goal - pts.reshape(-1, 6)
        solved = e.norm(dim=-1).reshape(K, starts).min(dim=-1).values < 1e-7
        if bool(solved.reshape(-1, group or K).all(dim=-1).any()):
            break
        q = _damped_step(
            q, J, e, (lo + margin * span, hi - margin * span), _MU * 0.1 * (mid - q) / span
        )
    err = (goal - kin.points(q).reshape(-1, 6)).norm(dim=-1).reshape(K, starts)
    q = q.reshape(K, starts, n)
    ok = err < torch.clamp(err.min(dim=-1, keepdim=True).values * 1.01 + 1e-9, min=1e-4)
    centred = ((q - mid).abs() / span).max(dim=-1).values
    best = torch.where(ok, centred, torch.full_like(centred, float("inf"))).argmin(dim=-1)
    rows = torch.arange(K, device=kin.device)
    return q[rows, best], err[rows, best]


def dexterity(jacobian: Tensor, rank: int) -> Tensor:
    """How freely the arm moves the peg: the ``rank``-th largest singular value of the point
    Jacobian ``[..., 6, n]`` (m/rad) -> ``[...]``, ``rank`` being the Jacobian's rank at a
    generic pose (:func:`generic_rank`).

    Two points a fixed distance apart have at most 5 degrees of freedom (turning about the line
    through them moves neither), fewer on arms with fewer joints or a wrist that rolls about
    the peg, so the ``rank``-th singular value is the slowest that joint rates of 1 rad/s move
    the peg in its worst direction among those the arm has; it is 0 at a singular pose."""
    return torch.linalg.svdvals(jacobian)[..., rank - 1]


def generic_rank(kin: PegKinematics, q: Tensor) -> int:
    """The point Jacobian's rank at generic poses: its largest numerical rank (singular values
    above 1e-6 of the largest) over the poses ``q: [P, n]``, at most 5."""
    values = torch.linalg.svdvals(kin.points_and_jacobian(q)[1])
    rank = (values > 1e-6 * values[..., :1]).sum(dim=-1)
    return min(5, int(rank.max()))


def follow(
    kin: PegKinematics, arm: ArmSpec, q0: Tensor, targets: Tensor, rank: int
) -> tuple[Tensor, Tensor]:
    """Track point targets ``[M, 2, 3]`` from the pose ``q0: [n]`` continuously, as a controller
    starting there would: the targets move along the straight line from q0's points in
    :data:`_PATH_STEPS` way points, each reached by damped least squares from the last pose
    (the steps of :func:`solve_ik_batch` without its mid-range drift), within the joint limits
    themselves (the placement's margin keeps the poses it places off the limits, not the way
    between them: with the margin, a published SO-101's seed-2 stream was refused, its arm
    passing within 5 % of a limit on the way to one floor).  Returns the point error (m) at the
    end and the least :func:`dexterity` of ``rank`` on the way, ``[M]`` each."""
    lo = torch.tensor(arm.lower, dtype=torch.float64, device=kin.device)
    hi = torch.tensor(arm.upper, dtype=torch.float64, device=kin.device)
    start = kin.points(q0)  # [2, 3]
    q = q0.expand(targets.shape[0], -1).clone()
    least = torch.full((targets.shape[0],), math.inf, dtype=torch.float64, device=kin.device)
    for step in range(1, _PATH_STEPS + 1):
        goal = (start + (targets - start) * step / _PATH_STEPS).reshape(-1, 6)
        for _ in range(_PATH_ITERATIONS):
            pts, J = kin.points_and_jacobian(q)
            e = goal - pts.reshape(-1, 6)
            if bool((e.norm(dim=-1) < 1e-7).all()):
                break
            q = _damped_step(q, J, e, (lo, hi))
        least = torch.minimum(least, dexterity(kin.points_and_jacobian(q)[1], rank))
    error = (targets.reshape(-1, 6) - kin.points(q).reshape(-1, 6)).norm(dim=-1)
    return error, least
