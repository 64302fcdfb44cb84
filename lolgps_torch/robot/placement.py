"""Where the hole goes and where the arm starts, derived from the arm itself.

A task pose is fixed by the two peg points: the tip at a point ``c`` and the top at
``c + s e_z`` (s the point separation), i.e. the peg vertical, pointing down.  Inverse
kinematics solves ``min_q |p(q) - p*|^2`` by damped least squares
(Levenberg-Marquardt steps ``dq = (J^T J + mu I)^{-1} (J^T e + 0.1 mu (q_mid - q) / span)``,
whose last term drifts the redundant directions towards mid-range) from several starts in one
batch, and keeps the converged solution furthest inside the joint limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import ArmSpec
from lolgps_torch.robot.kinematics import PegKinematics


@dataclass(frozen=True)
class PlacementConfig:
    """Automatic placement of the hole and the start pose (m).

    :param reach_fraction: nominal hole's horizontal distance from the base, as a fraction of
        the arm's reach measured from its second actuated joint.
    :param mouth_below_shoulder: hole mouth height below the shoulder, as a fraction of reach.
    :param start_offset: peg tip at the start pose relative to the nominal hole mouth.
    :param q0: explicit start pose (rad); derived by inverse kinematics when None.
    :param ik_tolerance: largest point error (m) accepted as reached.
    :param limit_margin: fraction of each joint's range kept free at both ends.
    """

    reach_fraction: float = 0.55
    mouth_below_shoulder: float = 0.15
    start_offset: tuple[float, float, float] = (-0.10, 0.0, 0.20)
    q0: tuple[float, ...] | None = None
    ik_tolerance: float = 1e-3
    limit_margin: float = 0.05


@dataclass(frozen=True)
class TaskGeometry:
    """The nominal hole (mouth centre, world frame) and the start pose q0."""

    nominal_mouth: tuple[float, float, float]
    q0: tuple[float, ...]


def vertical_peg_targets(tip: Tensor, separation: float) -> Tensor:
    """Targets ``[..., 2, 3]`` for a peg whose tip is at ``tip: [..., 3]``, pointing down."""
    top = tip.clone()
    top[..., 2] = top[..., 2] + separation
    return torch.stack([tip, top], dim=-2)


def solve_ik(
    kin: PegKinematics, arm: ArmSpec, targets: Tensor, margin: float, iterations: int = 200
) -> tuple[Tensor, Tensor]:
    """Best IK solution for point targets ``[2, 3]``: returns ``(q [n], point error in m)``."""
    lo = torch.tensor(arm.lower, dtype=torch.float64, device=kin.device)
    hi = torch.tensor(arm.upper, dtype=torch.float64, device=kin.device)
    span, mid = hi - lo, (hi + lo) / 2
    gen = torch.Generator().manual_seed(0)
    starts = torch.rand(16, arm.dof, generator=gen, dtype=torch.float64).to(kin.device)
    q = lo + span * (0.2 + 0.6 * starts)
    q[0] = mid
    goal = targets.reshape(6)
    eye = torch.eye(arm.dof, dtype=torch.float64, device=kin.device)
    for _ in range(iterations):
        pts, J = kin.points_and_jacobian(q)
        e = goal - pts.reshape(-1, 6)
        if e.norm(dim=-1).min() < 1e-7:
            break
        mu = 1e-4
        JtJ = J.transpose(-1, -2) @ J + mu * eye
        rhs = (J.transpose(-1, -2) @ e[..., None])[..., 0] + mu * 0.1 * (mid - q) / span
        dq = torch.linalg.solve(JtJ, rhs)
        dq = dq * (0.2 / dq.norm(dim=-1, keepdim=True).clamp(min=0.2))  # trust region 0.2 rad
        q = (q + dq).clamp(lo + margin * span, hi - margin * span)
    err = (goal - kin.points(q).reshape(-1, 6)).norm(dim=-1)
    ok = err < max(1e-4, err.min().item() * 1.01 + 1e-9)
    centred = ((q - mid).abs() / span).max(dim=-1).values
    best = torch.where(ok, centred, torch.full_like(centred, float("inf"))).argmin()
    return q[best], err[best]


def reach(arm: ArmSpec, kin: PegKinematics) -> tuple[Tensor, float]:
    """Shoulder position (second actuated joint's origin at q = 0) and reach from it to the tip.

    Reach is approximated by the tip's farthest distance from the shoulder over random poses.
    """
    gen = torch.Generator().manual_seed(1)
    lo = torch.tensor(arm.lower, dtype=torch.float64)
    hi = torch.tensor(arm.upper, dtype=torch.float64)
    q = (lo + (hi - lo) * torch.rand(4096, arm.dof, generator=gen, dtype=torch.float64)).to(
        kin.device
    )
    frames = kin.chain.forward_kinematics(
        torch.zeros(1, arm.dof, dtype=torch.float64), end_only=False
    )
    joint_frames = kin.chain.get_joint_parent_frame_names()
    shoulder_frame = joint_frames[1] if arm.dof > 1 else joint_frames[0]
    shoulder = frames[shoulder_frame].get_matrix()[0, :3, 3].to(kin.device)
    tip = kin.points(q)[:, 0]
    return shoulder, float((tip - shoulder).norm(dim=-1).max())


def place_task(arm: ArmSpec, kin: PegKinematics, config: PlacementConfig) -> TaskGeometry:
    """Nominal hole within reach in front of the arm, and a start pose above and away from it."""
    shoulder, radius = reach(arm, kin)
    mouth = torch.stack(
        [
            shoulder[0] + config.reach_fraction * radius,
            shoulder[1],
            shoulder[2] - config.mouth_below_shoulder * radius,
        ]
    )
    if config.q0 is not None:
        if len(config.q0) != arm.dof:
            raise LolgpsError(f"--q0 needs {arm.dof} values, got {len(config.q0)}")
        q0 = config.q0
    else:
        start = mouth + torch.tensor(config.start_offset, dtype=torch.float64, device=kin.device)
        separation = -arm.point_offsets[1][2]
        q, err = solve_ik(kin, arm, vertical_peg_targets(start, separation), config.limit_margin)
        if err > config.ik_tolerance:
            raise LolgpsError(
                f"no start pose: the peg cannot point down at {start.tolist()} "
                f"(IK error {err:.3f} m); the arm may be too short to reach the table"
            )
        q0 = tuple(q.tolist())
    return TaskGeometry(nominal_mouth=tuple(mouth.tolist()), q0=q0)
