"""Where the hole goes and where the arm starts, derived from the arm itself and the stream.

A task pose is fixed by the two peg points: the tip at a point ``c`` and the top at
``c + s e_z`` (s the point separation), i.e. the peg vertical, pointing down, solved by the
batched inverse kinematics of :mod:`lolgps_torch.robot.ik`.

Placement.  With R the arm's reach from its shoulder (:func:`reach`), the nominal hole mouth
is tried at ``shoulder + (rho R cos a, rho R sin a, -eta R)`` for a grid of fractions
``(rho, eta)`` about ``(reach_fraction, mouth_below_shoulder)`` and azimuths a about the
base's +x, nearest first (:func:`~lolgps_torch.robot.spots.candidates`): first as it is, then
shifted by ``-c`` with ``c`` the centre of the stream's positions (so that they straddle the
spot).  Where none fits, heights further from the preferred one follow (``eta`` up to 0.9 R
below the shoulder and 0.3 R above it: arms that hang from a torso, or reach up to a table),
those whose targets lie nearest the sampled down-pointing tips first.  Where the grid has none
(``place_task``'s ``spots``), mouths are placed about the sampled tips themselves
(:func:`~lolgps_torch.robot.spots.cloud_candidates`), the start turned to every azimuth.
The first mouth at which the start pose and every position's hole floor are reachable with the
peg pointing down, inside the joint limits' margin, *and* every floor is reached from the start pose by
following the peg points along the straight line between them (:func:`follow`), never nearer
a singular pose than ``dexterity R``, is kept.  The second condition is what a local
controller can do: it moves the arm continuously from q0 and cannot flip an elbow or a wrist
to reach a floor that lies only on another inverse-kinematics branch.  Nothing but R scales
it; an arm placed as before (a = 0, the configured fractions, all reachable on q0's branch)
gets the same hole and start pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.ik import follow, generic_rank, solve_ik, solve_ik_batch
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.robot.spots import (
    FAR_HEIGHTS,
    FAR_START_SCALES,
    START_SCALES,
    STEPS,
    candidates,
    cloud_candidates,
    spread,
)

Position = tuple[float, float]
Spots = Literal["grid", "sampled", "both"]
_SAMPLES = 16384  # random poses for the down-pointing workspace
_REACH_SAMPLES = 4096  # the first of them, for the reach
_SCREEN = 0.1  # candidates are solved if every target is this near (x reach) a sampled tip
_VERIFIED = 24  # candidates solved in one IK batch
_CHUNKS = 4  # batches at most
_RANK_POSES = 64  # down-pointing poses for the point Jacobian's generic rank
_APART = 0.03  # (x reach) the last candidates verified differ by at least this much
_CDIST_ENTRIES = 1 << 22  # distances computed at once in the screening


@dataclass(frozen=True)
class PlacementConfig:
    """Automatic placement of the hole and the start pose (m).

    :param reach_fraction: nominal hole's preferred horizontal distance from the shoulder, as a
        fraction of the arm's reach measured from its second actuated joint.
    :param mouth_below_shoulder: preferred hole mouth height below the shoulder, as a fraction
        of reach.
    :param start_offset: peg tip at the start pose relative to the nominal hole mouth.
    :param q0: explicit start pose (rad); derived by inverse kinematics when None.
    :param mouth: the nominal hole mouth (m, world frame), fixed; derived by the placement when
        None.  A run folder records the mouth and q0 its task was placed at (:func:`pinned`),
        so that reading it back gives the same task whatever the placement of the code.
    :param ik_tolerance: largest point error (m) accepted as reached.
    :param limit_margin: fraction of each joint's range kept free at both ends.
    :param positions: the hole offsets (m) the placement must reach (the stream's conditions);
        the nominal position alone when empty.
    :param dexterity: the least dexterity (:func:`dexterity`) allowed on the way from the start
        pose to each hole floor, as a fraction of the arm's reach per radian.  Near 0 the arm
        is at a singular pose (a stretched elbow, aligned wrist axes), where its controllers
        cannot move the peg in some direction.  On a published UR5 the five positions that
        could not be followed from the start pose (4-24 mm short, dexterity at most 0.0075)
        were the five whose local controller or policy ended 17-105 mm from the target; the
        positions that learnt had 0.014-0.037 (docs/RESULTS.md at c902895, section 15).
    """

    reach_fraction: float = 0.55
    mouth_below_shoulder: float = 0.15
    start_offset: tuple[float, float, float] = (-0.10, 0.0, 0.20)
    q0: tuple[float, ...] | None = None
    mouth: tuple[float, float, float] | None = None
    ik_tolerance: float = 1e-3
    limit_margin: float = 0.05
    positions: tuple[Position, ...] = ()
    dexterity: float = 0.01

    def __post_init__(self) -> None:
        if not 0.0 < self.reach_fraction < 1.0:
            raise LolgpsError(f"reach fraction must be in (0, 1), got {self.reach_fraction}")
        if not -1.0 < self.mouth_below_shoulder < 1.0:
            raise LolgpsError(
                f"mouth height below the shoulder must be in (-1, 1) reach, got "
                f"{self.mouth_below_shoulder}"
            )
        if len(self.start_offset) != 3 or not all(map(math.isfinite, self.start_offset)):
            raise LolgpsError(f"start offset needs 3 finite numbers, got {self.start_offset}")
        if self.mouth is not None and (
            len(self.mouth) != 3 or not all(map(math.isfinite, self.mouth))
        ):
            raise LolgpsError(f"the hole mouth needs 3 finite numbers (m), got {self.mouth}")
        if self.q0 is not None and not all(map(math.isfinite, self.q0)):
            raise LolgpsError(f"--q0 must be finite numbers (rad), got {list(self.q0)}")
        if not self.ik_tolerance > 0:
            raise LolgpsError(f"IK tolerance must be positive, got {self.ik_tolerance}")
        if not 0.0 <= self.limit_margin < 0.5:
            raise LolgpsError(f"limit margin must be in [0, 0.5), got {self.limit_margin}")
        if not 0.0 <= self.dexterity < 1.0:
            raise LolgpsError(f"dexterity must be in [0, 1) reach per radian, got {self.dexterity}")
        positions = tuple((float(p[0]), float(p[1])) for p in self.positions)
        if any(len(p) != 2 for p in self.positions) or not all(
            math.isfinite(v) for p in positions for v in p
        ):
            raise LolgpsError("hole positions must be finite (dx, dy) pairs (m)")
        object.__setattr__(self, "positions", positions)


@dataclass(frozen=True)
class TaskGeometry:
    """The nominal hole (mouth centre, world frame) and the start pose q0."""

    nominal_mouth: tuple[float, float, float]
    q0: tuple[float, ...]


def pinned(config: PlacementConfig, geometry: TaskGeometry) -> PlacementConfig:
    """``config`` with the hole mouth and the start pose fixed at ``geometry``'s."""
    return replace(config, mouth=geometry.nominal_mouth, q0=geometry.q0)


def vertical_peg_targets(tip: Tensor, separation: float) -> Tensor:
    """Targets ``[..., 2, 3]`` for a peg whose tip is at ``tip: [..., 3]``, pointing down."""
    top = tip.clone()
    top[..., 2] = top[..., 2] + separation
    return torch.stack([tip, top], dim=-2)


def reach(arm: ArmSpec, kin: PegKinematics) -> tuple[Tensor, float]:
    """Shoulder position (second actuated joint's origin at q = 0) and reach from it to the tip.

    Reach is approximated by the tip's farthest distance from the shoulder over random poses.
    """
    shoulder, radius, _, _ = _workspace(arm, kin)
    return shoulder, radius


def _workspace(arm: ArmSpec, kin: PegKinematics) -> tuple[Tensor, float, Tensor, Tensor]:
    """Shoulder, reach, and the random poses ``q [P, n]`` (within the limits' margin) whose peg
    points within 30 degrees of straight down, with their tips ``[P, 3]``."""
    gen = torch.Generator().manual_seed(1)
    lo = torch.tensor(arm.lower, dtype=torch.float64)
    hi = torch.tensor(arm.upper, dtype=torch.float64)
    q = (lo + (hi - lo) * torch.rand(_SAMPLES, arm.dof, generator=gen, dtype=torch.float64)).to(
        kin.device
    )
    frames = kin.chain.forward_kinematics(
        torch.zeros(1, arm.dof, dtype=torch.float64), end_only=False
    )
    joint_frames = kin.chain.get_joint_parent_frame_names()
    shoulder_frame = joint_frames[1] if arm.dof > 1 else joint_frames[0]
    shoulder = frames[shoulder_frame].get_matrix()[0, :3, 3].to(kin.device)
    points = kin.points(q)  # [S, 2, 3]
    tip = points[:, 0]
    along = (points[:, 0] - points[:, 1]) / -arm.point_offsets[1][2]  # unit, top to tip
    down = along[:, 2] < -math.cos(math.radians(30.0))
    radius = float((tip[:_REACH_SAMPLES] - shoulder).norm(dim=-1).max())
    return shoulder, radius, q[down], tip[down]


_PLACED: dict[tuple[object, ...], TaskGeometry] = {}  # place_task's answers in this process
_PLACED_KEPT = 32


def place_task(
    arm: ArmSpec, kin: PegKinematics, config: PlacementConfig, depth: float, spots: Spots = "both"
) -> TaskGeometry:
    """The first nominal hole (module docstring) at which the start pose and the floor of the
    hole at every position are reachable with the peg pointing down; the start pose from IK
    (or ``config.q0``).  A :class:`LolgpsError` naming what to change when there is none.
    With ``config.mouth`` given, that mouth and its start pose, without a search.

    The candidates are screened by how near each target lies to the random down-pointing
    poses' tips; the preferred one, then the screened ones in order, are solved by IK in
    batches, each target started from mid-range, from the pose of its nearest sampled tip and
    from random poses.

    :param depth: the hole's depth (m): the tip's target is that far below the mouth.
    :param spots: the candidates searched: the grid about the preferred spot, the spots about
        the sampled tips (:func:`~lolgps_torch.robot.spots.cloud_candidates`), or both, in
        that order.

    The search is a function of its arguments alone (its random poses and IK starts come from
    generators of fixed seeds), so its answer is kept for the process: the tasks, run folders
    and probes of one arm share one search (``kin`` is ``PegKinematics(arm)`` on its device;
    where the arm's file lies places nothing, so a run folder's copy shares its original's).
    """
    described = tuple(getattr(arm, f.name) for f in fields(arm) if f.name != "source_path")
    key = (described, config, depth, spots, kin.device, torch.get_num_threads())
    if key not in _PLACED:
        if len(_PLACED) >= _PLACED_KEPT:
            del _PLACED[next(iter(_PLACED))]
        _PLACED[key] = _place(arm, kin, config, depth, spots)
    return _PLACED[key]


def _place(
    arm: ArmSpec, kin: PegKinematics, config: PlacementConfig, depth: float, spots: Spots
) -> TaskGeometry:
    """:func:`place_task` without its memory."""
    if spots not in ("grid", "sampled", "both"):
        raise LolgpsError(f"placement spots must be grid, sampled or both, got {spots!r}")
    if config.q0 is not None and len(config.q0) != arm.dof:
        raise LolgpsError(f"--q0 needs {arm.dof} values, got {len(config.q0)}")
    if config.mouth is not None:
        mouth = torch.tensor(config.mouth, dtype=torch.float64, device=kin.device)
        return _geometry(arm, kin, config, mouth, torch.tensor(config.start_offset).to(mouth))
    shoulder, radius, cloud_q, cloud_tip = _workspace(arm, kin)
    positions = torch.tensor(config.positions or ((0.0, 0.0),), dtype=torch.float64)
    positions = positions.to(kin.device)
    floor = torch.nn.functional.pad(positions, (0, 1), value=-depth)  # [M, 3] below the mouth
    if cloud_tip.shape[0] == 0:
        raise LolgpsError(_cannot_point_down(arm, radius))
    rank = generic_rank(kin, cloud_q[:_RANK_POSES])
    search = _Search(arm, kin, config, floor, (cloud_q, cloud_tip), (radius, rank))
    found = None
    if spots != "sampled":
        preferred = (config.reach_fraction, config.mouth_below_shoulder, config.start_offset)
        near_mouths, near_starts = candidates(
            shoulder, radius, positions, preferred, (STEPS, START_SCALES)
        )
        far_mouths, far_starts = candidates(
            shoulder, radius, positions, preferred, (FAR_HEIGHTS, FAR_START_SCALES)
        )
        mouths = torch.cat([near_mouths, far_mouths])  # [C, 3]
        start_offsets = torch.cat([near_starts, far_starts])
        tips, gap, score = search.screen(mouths, start_offsets)
        screened = [c for c in range(1, len(mouths)) if score[c] <= _SCREEN * radius]
        near = [c for c in screened if c < len(near_mouths)]
        far = sorted((c for c in screened if c >= len(near_mouths)), key=lambda c: float(score[c]))
        chunks = [[0]]  # the preferred spot alone first, then the near ones in order, the far
        for group in (near, far):
            chunks += [group[i : i + _VERIFIED] for i in range(0, len(group), _VERIFIED)][:_CHUNKS]
        found = search.verify(chunks, mouths, start_offsets, tips, gap)
    if found is None and spots != "grid":  # about the sampled tips, wherever the arm points down
        mouths, start_offsets = cloud_candidates(cloud_tip, positions, depth, config.start_offset)
        tips, gap, score = search.screen(mouths, start_offsets)
        order = [int(c) for c in score.argsort() if score[c] <= _SCREEN * radius]
        best = spread(mouths, start_offsets, order, _APART * radius, _CHUNKS * _VERIFIED)
        chunks = [best[i : i + _VERIFIED] for i in range(0, len(best), _VERIFIED)]
        found = search.verify(chunks, mouths, start_offsets, tips, gap)
    if found is not None:
        return found
    raise LolgpsError(
        _refusal(arm, config, radius, positions, search.reached, search.holes_only, search.stuck)
    )


class _Search:
    """The verification of candidate mouths: which are screened in, which are solved by IK in
    batches, and what the best of them reached (for the refusal).

    :param floor: the hole floors ``[M, 3]`` relative to the mouth.
    :param cloud: the down-pointing sampled poses ``[P, n]`` and their tips ``[P, 3]``.
    :param scale: the reach (m) and the point Jacobian's generic rank.
    """

    def __init__(
        self,
        arm: ArmSpec,
        kin: PegKinematics,
        config: PlacementConfig,
        floor: Tensor,
        cloud: tuple[Tensor, Tensor],
        scale: tuple[float, int],
    ) -> None:
        self.arm, self.kin, self.config, self.floor = arm, kin, config, floor
        self.cloud_q, self.cloud_tip = cloud
        self.scale = scale
        self.reached = (0, floor.shape[0] + (config.q0 is None))  # most targets reached, of
        self.holes_only = False  # all holes reached, but not the start
        self.stuck: tuple[list[float], float, float] | None = None  # reachable, not from q0

    def screen(self, mouths: Tensor, starts: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The targets ``[C, K, 3]`` of the mouths ``[C, 3]`` (the start tip first), each
        target's nearest sampled tip, and each mouth's farthest such gap ``[C]``."""
        tips = mouths[:, None] + self.floor  # [C, M, 3]
        if self.config.q0 is None:
            tips = torch.cat([(mouths + starts)[:, None], tips], dim=1)  # [C, K, 3]
        rows = tips.reshape(-1, 3)
        block = max(1, _CDIST_ENTRIES // self.cloud_tip.shape[0])
        gaps = [
            torch.cdist(rows[i : i + block], self.cloud_tip).min(dim=-1)
            for i in range(0, len(rows), block)
        ]
        gap = torch.cat([g.values for g in gaps])
        nearest = torch.cat([g.indices for g in gaps])
        return tips, nearest, gap.reshape(tips.shape[:2]).max(dim=-1).values

    def verify(
        self,
        chunks: list[list[int]],
        mouths: Tensor,
        starts: Tensor,
        tips: Tensor,
        nearest: Tensor,
    ) -> TaskGeometry | None:
        """The first candidate of ``chunks`` (in order) whose targets are all solved and whose
        floors are followed from its start pose (:func:`_unfollowed`), or None."""
        arm, kin, config = self.arm, self.kin, self.config
        for chosen in chunks:
            targets = vertical_peg_targets(tips[chosen].reshape(-1, 3), -arm.point_offsets[1][2])
            seeds = self.cloud_q[nearest.reshape(tips.shape[:2])[chosen].reshape(-1)]
            q, err = solve_ik_batch(
                kin, arm, targets, config.limit_margin, 150, 6, seeds, group=tips.shape[1]
            )
            ok = (err <= config.ik_tolerance).reshape(len(chosen), -1)
            for row, candidate in enumerate(chosen):
                if bool(ok[row].all()):
                    geometry = _geometry(arm, kin, config, mouths[candidate], starts[candidate])
                    floors = mouths[candidate] + self.floor
                    miss = _unfollowed(arm, kin, config, geometry.q0, floors, self.scale)
                    if miss is None:
                        return geometry
                    offset = self.floor[miss[0], :2].tolist()
                    self.stuck = self.stuck or (offset, miss[1], miss[2])
            self.reached = (max(self.reached[0], int(ok.sum(dim=-1).max())), ok.shape[1])
            self.holes_only = self.holes_only or (
                config.q0 is None and bool(ok[:, 1:].all(dim=-1).any())
            )
        return None


def _refusal(
    arm: ArmSpec,
    config: PlacementConfig,
    radius: float,
    positions: Tensor,
    reached: tuple[int, int],
    holes_only: bool,
    stuck: tuple[list[float], float, float] | None,
) -> str:
    """Why no nominal hole fits, for the error: nothing reached; every hole reached but not
    from the start pose (``stuck``: the worst position, its error and dexterity); the holes
    but not the start; or at best ``reached = (targets, of)``."""
    if reached[0] == 0:
        return _cannot_point_down(arm, radius)
    if stuck is not None:
        (dx, dy), error, least = stuck
        return (
            f"the hole positions are reachable with the peg pointing down, but not all from the "
            f"start pose without passing a singular pose: at ({dx:+.3f}, {dy:+.3f}) m the peg "
            f"ends {1000 * error:.0f} mm short and the arm's dexterity falls to "
            f"{least / radius:.3f} of its reach per radian (at least {config.dexterity} is "
            f"needed): use closer positions (--conditions, --stream) or give the start pose (--q0)"
        )
    if holes_only:
        return (
            f"no start pose: the hole positions are reachable with the peg pointing down, but "
            f"not the start {config.start_offset[2]:.2f} m (or a half or a quarter of that) above the hole within "
            f"this arm's reach ({radius:.2f} m): use a shorter peg (--peg-length) or give the "
            f"start pose (--q0)"
        )
    spread = float((positions.max(dim=0).values - positions.min(dim=0).values).norm())
    return (
        f"the {positions.shape[0]} hole positions (spread {spread:.2f} m) and the start pose do "
        f"not fit in the reach of this arm ({radius:.2f} m) with the peg pointing down: at best "
        f"{reached[0]} of {reached[1]} reachable; use closer positions (--conditions, --stream, "
        f"--scale) or a shorter peg (--peg-length)"
    )


def _unfollowed(
    arm: ArmSpec,
    kin: PegKinematics,
    config: PlacementConfig,
    q0: tuple[float, ...],
    floors: Tensor,
    scale: tuple[float, int],
) -> tuple[int, float, float] | None:
    """None if :func:`follow` reaches every hole floor ``[M, 3]`` from ``q0`` within the IK
    tolerance, its dexterity never below ``config.dexterity`` times the reach; else the worst
    position's index, its point error (m) and its least dexterity (m/rad): the farthest short
    if one is short, else the least dexterous.  ``scale``: the reach (m) and the Jacobian's
    generic rank."""
    radius, rank = scale
    start = torch.tensor(q0, dtype=torch.float64, device=kin.device)
    holes = vertical_peg_targets(floors, -arm.point_offsets[1][2])
    error, least = follow(kin, arm, start, holes, rank)
    far = error > config.ik_tolerance
    if not bool((far | (least < config.dexterity * radius)).any()):
        return None
    worst = int(error.argmax() if bool(far.any()) else least.argmin())
    return worst, float(error[worst]), float(least[worst])


def _geometry(
    arm: ArmSpec, kin: PegKinematics, config: PlacementConfig, mouth: Tensor, offset: Tensor
) -> TaskGeometry:
    """The nominal mouth and the start pose: ``config.q0``, or the IK solution furthest inside
    the limits for the peg tip at ``mouth + offset``, pointing down."""
    if config.q0 is not None:
        return TaskGeometry(nominal_mouth=tuple(mouth.tolist()), q0=config.q0)
    start = mouth + offset
    targets = vertical_peg_targets(start, -arm.point_offsets[1][2])
    q, err = solve_ik(kin, arm, targets, config.limit_margin)
    if err > config.ik_tolerance:  # the screening solved it; a miss here is a numerical fluke
        raise LolgpsError(f"no start pose: IK error {float(err):.3f} m at {start.tolist()}")
    return TaskGeometry(nominal_mouth=tuple(mouth.tolist()), q0=tuple(q.tolist()))


def _cannot_point_down(arm: ArmSpec, radius: float) -> str:
    return (
        f"no start pose: the peg cannot point down at the table anywhere within the arm's "
        f"reach ({radius:.2f} m): the arm may be too short for the peg (--peg-length), or the "
        f"peg may point along the wrong axis of {arm.ee_link!r} (--peg-axis, now "
        f"{arm.peg_axis or 'carried by the URDF'}; or --ee-link)"
    )
