"""What the method needs to know about a URDF arm, read once with yourdfpy after the XML has
been checked against what PyBullet and pytorch-kinematics need (:mod:`.validate`).

yourdfpy (and trimesh, which it imports) is imported only when a URDF is parsed, and the
:class:`ArmSpec` itself lives in :mod:`.spec`, so processes that merely receive one (the
evaluation's workers) do not pay for them.

An :class:`ArmSpec` is the single description that drives both PyBullet (joint names are
mapped to body joint indices) and pytorch-kinematics (the serial chain to the point
frame), so the two cannot disagree; the peg it ends in is :mod:`.peg`'s.

The module is one concern, turning a published URDF into that description, and its parts are
the loader's steps in order: the chain from the base link to the end effector, the joints held
off it, the derived effort limits, and the text both readers accept (meshes resolved, unused
shapes and other tools' extensions dropped); it stays whole for that reason.
"""

from __future__ import annotations

import functools
import hashlib
import io
import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.effort import (
    EFFORT_MARGIN,
    JOINT_SPEED,
    TIP_SPEED,
    derived_effort,
    derived_velocity,
)
from lolgps_torch.robot.packages import resolve_mesh
from lolgps_torch.robot.peg import (
    ATTACHED_PEG,
    ATTACHED_PEG_TIP,
    CARRIED_PEG_TIP,
    PegConfig,
    attach_peg,
    auto_axis,
    carried_peg_radius,
)
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import (
    INERTIA_ENTRIES,
    INERTIA_KEYS,
    ArmSpec,
    add_inertial,
)
from lolgps_torch.robot.validate import (
    ArmWarning,
    check_actuated_limit,
    check_moved_mass,
    validate_urdf,
)

if TYPE_CHECKING:
    import yourdfpy

_ACTUATED = ("revolute", "continuous")
_HELD = ("revolute", "continuous", "prismatic")
PYBULLET_LINKS = 128  # PyBullet keeps the link states of a body of at most so many links  # the moving joints a position can be held at
# a prefix of an element's or attribute's name, as in <drake:member> or drake:acceleration="..."
_PREFIXED = re.compile(r"(?:<|</|\s)([A-Za-z_][\w.-]*):[A-Za-z_][\w.-]*(?=[\s=/>])")
# mesh file extensions PyBullet reads (any case)
_MESH_FORMATS = (".stl", ".obj", ".dae", ".cdf", ".vtk")
# words published descriptions use in the joint names of grippers and hands
_GRIPPER_WORDS = ("finger", "grip", "jaw", "knuckle", "claw", "thumb")
# words in the link names of sensors mounted on a wrist, which are no tool frame
_SENSOR_WORDS = ("camera", "optical", "imu", "accel", "lidar", "laser", "range", "depth")


def load_arm(
    path: str,
    ee_link: str | None = None,
    peg: PegConfig | None = None,
    package_path: Sequence[str] = (),
    base_link: str | None = None,
    hold: Mapping[str, float] | None = None,
    mjcf: bool = False,
) -> ArmSpec:
    """Read and validate a URDF arm; raise :class:`LolgpsError` with a one-line reason.

    :param path: the URDF file, as published (``package://`` mesh URIs are searched for, see
        :mod:`.packages`; meshes that are not found are only warned about).
    :param ee_link: the end-effector link; detected below ``base_link`` when None
        (:func:`_detect_ee_link`).
    :param peg: the peg attached when the URDF carries none.
    :param package_path: folders searched for ROS packages after ``ROS_PACKAGE_PATH``.
    :param base_link: the link the arm's chain starts from (the root when None); every joint
        above it is held fixed, as is every joint off the chain.
    :param hold: positions (rad or m) of held joints; the others are held at 0, or at the
        middle of their limits when 0 is outside them.
    :param mjcf: ``path`` is an MJCF file, converted to URDF (:mod:`.mjcf`).
    """
    peg = peg or PegConfig()
    raw, tree, robot, root = _parse(path, package_path, mjcf)
    parent_joint = {j.child: j for j in robot.robot.joints}
    links = [link.name for link in robot.robot.links]
    start, ee_link, chain = _arm_chain(robot, root, path, ee_link, base_link)
    actuated = _actuated_joints(chain, ee_link)
    elements = {j.get("name"): j for j in tree.findall("joint")}
    unknown = [
        j.name
        for j in actuated
        if check_actuated_limit(elements[j.name], f"{path}: joint {j.name!r}")
    ]
    held = _lock_joints(tree, {j.name for j in actuated}, dict(hold or {}))

    carries_peg = CARRIED_PEG_TIP in links and ee_link == CARRIED_PEG_TIP
    if carries_peg:
        point_link, peg_link = CARRIED_PEG_TIP, parent_joint[CARRIED_PEG_TIP].parent
        peg_radius = carried_peg_radius(robot, peg_link, path)
    else:
        if ATTACHED_PEG in links:
            raise LolgpsError(
                f"{path}: link name {ATTACHED_PEG!r} is reserved for the attached peg"
            )
        point_link, peg_link, peg_radius = ATTACHED_PEG_TIP, ATTACHED_PEG, peg.radius
    kept = {root, ee_link, point_link, peg_link, *(n for j in chain for n in (j.parent, j.child))}
    _merge_fixed_leaves(tree, kept, PYBULLET_LINKS - (0 if carries_peg else 2), path)
    text = _portable_text(tree, path, package_path, peg_link)
    axis = ""
    if not carries_peg:
        axis = auto_axis(chain, actuated) if peg.axis == "auto" else peg.axis
        text = attach_peg(text, ee_link, peg, axis)
    massless = check_moved_mass(text, path)

    lims = [_limits(j) for j in actuated]
    arm = ArmSpec(
        urdf_text=text,
        source_path=os.path.abspath(path),
        source_sha256=hashlib.sha256(raw).hexdigest(),
        root_link=root,
        ee_link=ee_link,
        point_link=point_link,
        peg_link=peg_link,
        joint_names=tuple(j.name for j in actuated),
        lower=tuple(lim[0] for lim in lims),
        upper=tuple(lim[1] for lim in lims),
        effort=tuple(lim[2] for lim in lims),
        velocity=tuple(lim[3] for lim in lims),
        point_offsets=((0.0, 0.0, 0.0), (0.0, 0.0, -peg.point_separation)),
        peg_radius=peg_radius,
        peg_axis=axis,
        base_link=start,
        held=held,
        unbounded=tuple(j.name for j in actuated if not _bounded(j)),
    )
    if massless:
        _check_mass_matrix(arm, massless, path)
    slow = [j.name for j, lim in zip(actuated, lims, strict=True) if lim[3] == 0.0]
    return _with_derived_limits(arm, unknown, slow, path) if unknown or slow else arm


def _arm_chain(
    robot: yourdfpy.URDF, root: str, path: str, ee_link: str | None, base_link: str | None
) -> tuple[str, str, list[yourdfpy.Joint]]:
    """The arm's base link (``base_link``, else the root), its end-effector link (``ee_link``,
    else detected below the base link) and the joints from the base link to the end effector;
    unknown links, and a base link off the path from the root to the end effector, are
    errors."""
    parent_joint = {j.child: j for j in robot.robot.joints}
    links = [link.name for link in robot.robot.links]
    if not any(j.type in _ACTUATED for j in robot.robot.joints):
        raise LolgpsError(f"{path}: URDF has no revolute or continuous joints to actuate")
    if base_link is not None and base_link not in links:
        raise LolgpsError(f"unknown base link {base_link!r}; links are: {', '.join(links)}")
    start = base_link or root
    if ee_link is None:
        ee_link = _detect_ee_link(robot, start, path)
    elif ee_link not in links:
        raise LolgpsError(f"unknown end-effector link {ee_link!r}; links are: {', '.join(links)}")
    full, link = [], ee_link
    while link in parent_joint:
        full.append(parent_joint[link])
        link = parent_joint[link].parent
    full.reverse()
    above = [j.parent for j in full]
    if start not in (*above, ee_link):
        raise LolgpsError(
            f"base link {start!r} is not on the chain from the root to {ee_link!r}; the links "
            f"on it are: {', '.join(above)}"
        )
    return start, ee_link, full[above.index(start) :] if start in above else []


def _check_mass_matrix(arm: ArmSpec, massless: Sequence[str], path: str) -> None:
    """With massless driven links, joints can together make a motion that moves no mass (a
    massless wrist whose axes align): the mass matrix is then singular and no simulator can
    integrate the arm.  Checked at q = 0 (where the simulated world starts) and at random
    poses within the limits, with the inertias PyBullet uses."""
    lower, upper = (torch.tensor(b, dtype=torch.float64) for b in (arm.lower, arm.upper))
    draw = torch.rand(8, arm.dof, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    poses = torch.cat(
        [torch.zeros(1, arm.dof, dtype=torch.float64), lower + (upper - lower) * draw]
    )
    M = ArmDynamics(arm, inertia="pybullet").mass_matrix(poses)
    eig = torch.linalg.eigvalsh(M)
    singular = eig[:, 0] <= 1e-12 * eig[:, -1].clamp(min=1e-300)
    if bool(singular.any()):
        q = poses[int(torch.nonzero(singular)[0, 0])].tolist()
        raise LolgpsError(
            f"{path}: with link(s) {', '.join(map(repr, massless))} massless (no <inertial> "
            f"or mass 0) the mass matrix is singular at q = "
            f"[{', '.join(f'{v:.3g}' for v in q)}] rad (some joint motion moves no mass); "
            f"add their mass and inertia"
        )


def _with_derived_limits(
    arm: ArmSpec, effort: Sequence[str], velocity: Sequence[str], path: str
) -> ArmSpec:
    """``arm`` with the torque limits of the joints ``effort`` and the velocity limits of the
    joints ``velocity`` (each published as 0 or not at all) derived from the arm
    (:mod:`.effort`), in its URDF text too; one :class:`ArmWarning` per kind names the values
    used."""
    derived = {"effort": dict(zip(arm.joint_names, arm.effort, strict=True)),
               "velocity": dict(zip(arm.joint_names, arm.velocity, strict=True))}  # fmt: skip
    tree = ET.fromstring(arm.urdf_text)
    kinds = (
        ("effort", effort, derived_effort, "N m", f"{EFFORT_MARGIN:g} x the larger of the "
         "joint's largest gravity torque and the torque that accelerates its load at g / reach"),
        ("velocity", velocity, derived_velocity, "rad/s", f"the speed that moves the peg tip "
         f"at {TIP_SPEED:g} m/s, at most {JOINT_SPEED:g} rad/s (or give --velocity-limit)"),
    )  # fmt: skip
    joints = {joint.get("name"): joint for joint in tree.findall("joint")}
    for attr, names, derive, unit, how in kinds:
        values = dict(zip(arm.joint_names, derive(arm), strict=True)) if names else {}
        for name in names:
            derived[attr][name] = values[name]
            limit = joints[name].find("limit")
            if limit is None:  # a continuous joint published without one
                limit = ET.SubElement(joints[name], "limit")
            limit.set(attr, repr(values[name]))
            warnings.warn(
                f"{path}: joint {name!r}: <limit> {attr} is not given (0); using "
                f"{values[name]:.4g} {unit}, {how}; set {attr} to its real limit ({unit})",
                ArmWarning,
                stacklevel=3,
            )
    return replace(
        arm,
        urdf_text=ET.tostring(tree, encoding="unicode"),
        effort=tuple(derived["effort"][n] for n in arm.joint_names),
        velocity=tuple(derived["velocity"][n] for n in arm.joint_names),
    )


def _parse(
    path: str, package_path: Sequence[str], mjcf: bool = False
) -> tuple[bytes, ET.Element, yourdfpy.URDF, str]:
    """The file's bytes, its XML tree, yourdfpy's model and the root link; one-line errors for
    bad files, raised before yourdfpy, pytorch-kinematics or PyBullet read them.  ``mjcf``:
    the file is MJCF, read as the URDF :func:`~lolgps_torch.robot.mjcf.mjcf_urdf` makes of it."""
    import yourdfpy  # here, not at the top: see the module docstring

    if not os.path.isfile(path):
        raise LolgpsError(f"{'MJCF' if mjcf else 'URDF'} not found: {path}")
    with open(path, "rb") as fh:
        raw = fh.read()
    if mjcf:
        from lolgps_torch.robot.mjcf import mjcf_urdf  # imports MuJoCo, an extra

        text = mjcf_urdf(path)
    else:
        text = declare_prefixes(raw.decode("utf-8", errors="replace"))
    if "<!ENTITY" in text:
        raise LolgpsError(f"{path}: URDF declares XML entities; they are not resolved")
    try:
        tree = ET.fromstring(text)
    except ET.ParseError as exc:
        raise LolgpsError(f"{path}: malformed XML ({exc})") from None
    root = validate_urdf(tree, path)
    try:
        robot = yourdfpy.URDF.load(
            io.BytesIO(text.encode("utf-8")),
            build_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
            filename_handler=lambda name: resolve_mesh(name, path, package_path) or name,
        )
    except Exception as exc:  # yourdfpy raises assorted types on schema errors
        raise LolgpsError(f"{path}: not a valid URDF ({type(exc).__name__}: {exc})") from None
    return raw, tree, robot, root


def declare_prefixes(text: str) -> str:
    """``text`` with a namespace declared on ``<robot>`` for every prefix it uses undeclared.

    Descriptions written for one tool carry that tool's extensions under a prefix they often
    do not declare (``<limit drake:acceleration=...>``, ``<drake:collision_filter_group>``);
    the XML is then not well formed, though the URDF readers skip what they do not know.  The
    declared elements and attributes are dropped later (:func:`_portable_text`)."""
    used = set(_PREFIXED.findall(text)) - {"xml", "xmlns"}
    declared = set(re.findall(r"xmlns:([A-Za-z_][\w.-]*)\s*=", text))
    missing = sorted(used - declared)
    start = re.search(r"<robot\b", text)
    if not missing or start is None:
        return text
    names = "".join(f' xmlns:{p}="urn:undeclared:{p}"' for p in missing)
    return text[: start.end()] + names + text[start.end() :]


def _is_arm_joint(j: yourdfpy.Joint) -> bool:
    """A joint the method actuates: revolute or continuous, driven by itself (no mimic)."""
    return j.type in _ACTUATED and j.mimic is None


def _actuated_joints(chain: list[yourdfpy.Joint], ee_link: str) -> list[yourdfpy.Joint]:
    """The actuated joints of the chain from the base link to ``ee_link``; its mimic, prismatic
    and other joints are held."""
    actuated = [j for j in chain if _is_arm_joint(j)]
    if not actuated:
        raise LolgpsError(
            f"end-effector link {ee_link!r} is not downstream of any actuated joint below the "
            f"base link; name another with --ee-link (or --base-link)"
        )
    locked = [j.name for j in chain if j.type not in (*_ACTUATED, "fixed")]
    if locked:
        warnings.warn(
            f"joint(s) {', '.join(map(repr, locked))} on the chain to {ee_link!r} are held "
            f"fixed (--hold JOINT=VALUE sets where; --base-link LINK starts the arm below "
            f"them): only revolute and continuous joints are actuated",
            ArmWarning,
            stacklevel=3,
        )
    return actuated


def _limits(j: yourdfpy.Joint) -> tuple[float, float, float, float]:
    """(lower, upper, effort, velocity) of a checked joint (:func:`check_actuated_limit`;
    effort and velocity 0 where they are not given); continuous joints get [-pi, pi] for
    placement."""
    lim = j.limit
    if lim is None:  # a continuous joint published without a <limit>
        return -math.pi, math.pi, 0.0, 0.0
    if not _bounded(j):
        lower, upper = -math.pi, math.pi
    else:
        lower, upper = float(lim.lower), float(lim.upper)
    return lower, upper, float(lim.effort or 0.0), float(lim.velocity or 0.0)


def _bounded(j: yourdfpy.Joint) -> bool:
    """Whether the actuated joint ``j`` has position limits (not continuous, both given)."""
    lim = j.limit
    return j.type != "continuous" and lim is not None and None not in (lim.lower, lim.upper)


def _is_gripper(j: yourdfpy.Joint) -> bool:
    """A gripper's joint, by the words published descriptions use in their names (not in
    link names: several arms call their wrist link ``gripper_link``)."""
    return any(word in j.name.lower() for word in _GRIPPER_WORDS)


def _hand_drivers(children: dict[str, list[yourdfpy.Joint]]) -> set[str]:
    """The joints that a sibling joint (one of the same parent link) mimics: a hand's driving
    joint, whose fingers follow it (Romeo's ``LHand``, beside ``LFinger21``, ``LFinger31`` and
    ``LThumb1``), whatever its name."""
    return {
        j.mimic.joint
        for siblings in children.values()
        for j in siblings
        if j.mimic is not None and any(k.name == j.mimic.joint for k in siblings)
    }


def _detect_ee_link(robot: yourdfpy.URDF, root: str, path: str, grippers: bool = True) -> str:
    """The end of the arm: follow the actuated joints down from the root and stop at the link
    below which the tree splits into branches no deeper than the path so far (a hand or
    gripper) or has no actuated joint left; then take the deepest link fixed to it (a flange,
    tool or TCP frame; among equally deep ones, one with no child link), skipping gripper
    parts and wrist cameras.  Gripper joints (:func:`_is_gripper`, and a hand's driving joint,
    :func:`_hand_drivers`), mimic and prismatic joints never count,
    unless ``grippers`` is False: that is the second try when the first passes no actuated
    joint (a robot finger's joints are all named ``finger_...``).  Two equally deep arms are
    an error naming where each ends.
    """
    children: dict[str, list[yourdfpy.Joint]] = {}
    for j in robot.robot.joints:
        children.setdefault(j.parent, []).append(j)
    hands = _hand_drivers(children)

    def skipped(j: yourdfpy.Joint) -> bool:
        return grippers and (_is_gripper(j) or j.name in hands)

    @functools.cache
    def depth(link: str) -> int:  # most actuated joints on a path below link
        arm = [j for j in children.get(link, []) if not skipped(j)]
        return max((_is_arm_joint(j) + depth(j.child) for j in arm), default=0)

    def branches(link: str) -> list[tuple[int, str]]:
        arm = [j for j in children.get(link, []) if not skipped(j)]
        found = [(_is_arm_joint(j) + depth(j.child), j.child) for j in arm]
        return [(d, c) for d, c in found if d]

    def descend(link: str, passed: int) -> tuple[str, int]:
        """Down from ``link`` (``passed`` arm joints above it) to where the arm ends."""
        while branches(link):
            found = branches(link)
            best = max(d for d, _ in found)
            deepest = [c for d, c in found if d == best]
            if len(found) > 1 and passed >= best:
                break  # a hand below the arm
            if len(deepest) > 1:
                ends = [
                    _tool_frame(
                        children, descend(c, passed + _below_arm_joint(robot, c))[0], skipped
                    )
                    for c in deepest
                ]
                picks = " or ".join(f"--base-link {link} --ee-link {end}" for end in ends)
                raise LolgpsError(
                    f"{path}: the description has {len(deepest)} arms below link {link!r}, "
                    f"ending at {', '.join(ends)}: pick one with {picks}"
                )
            passed += _below_arm_joint(robot, deepest[0])
            link = deepest[0]
        return link, passed

    link, passed = descend(root, 0)
    if passed == 0 and grippers:
        return _detect_ee_link(robot, root, path, grippers=False)
    return _tool_frame(children, link, skipped)


def _tool_frame(
    children: dict[str, list[yourdfpy.Joint]],
    link: str,
    skipped: Callable[[yourdfpy.Joint], bool],
) -> str:
    """The deepest link fixed to ``link`` by joints not ``skipped``, breadth first, leaving out
    sensors (a wrist camera's links, by :data:`_SENSOR_WORDS`); among equally deep ones a frame
    with nothing below it (a tool frame, not a gripper's base), then the first found; ``link``
    itself if there is none."""
    fixed, frontier = [(0, link)], [(0, link)]
    while frontier:
        level, here = frontier.pop(0)
        for j in children.get(here, []):
            sensor = any(word in j.child.lower() for word in _SENSOR_WORDS)
            if j.type == "fixed" and not skipped(j) and not sensor:
                fixed.append((level + 1, j.child))
                frontier.append((level + 1, j.child))
    return max(fixed, key=lambda item: (item[0], item[1] not in children))[1]


def _below_arm_joint(robot: yourdfpy.URDF, link: str) -> bool:
    """Whether ``link`` hangs from an actuated joint (:func:`_is_arm_joint`)."""
    return _is_arm_joint(next(j for j in robot.robot.joints if j.child == link))


def _lock_joints(
    tree: ET.Element, keep: set[str], hold: dict[str, float]
) -> tuple[tuple[str, float], ...]:
    """Make every moving joint not in ``keep`` a fixed one at its held position (``hold``, else
    :func:`_rest_position`), folded into its ``<origin>``; drop the limits and mimic tags of
    fixed joints, which mean nothing here.  Returns the held joints and their positions; a
    ``hold`` naming no joint that can be held is a :class:`LolgpsError`."""
    joints = {j.get("name", ""): j for j in tree.findall("joint")}
    for name, value in hold.items():
        moves = name in joints and joints[name].get("type") in _HELD
        if name in keep or not moves:
            movable = [n for n, j in joints.items() if n not in keep and j.get("type") in _HELD]
            raise LolgpsError(
                f"--hold {name}={value:g}: not a joint that is held; the held joints are: "
                f"{', '.join(movable) or 'none'}"
            )
        _check_hold(joints[name], name, value)
    held = []
    for name, joint in joints.items():
        kind = joint.get("type") or ""
        if kind != "fixed" and name not in keep:
            q = hold[name] if name in hold else _rest_position(joint)
            if kind in _HELD:
                _fold_lock_position(joint, kind, q)
                held.append((name, q))
            joint.set("type", "fixed")
        if joint.get("type") == "fixed":
            for tag in ("limit", "mimic", "dynamics", "safety_controller", "calibration"):
                for part in joint.findall(tag):
                    joint.remove(part)
    return tuple(held)


def _joint_range(joint: ET.Element) -> tuple[float, float] | None:
    """A revolute or prismatic joint's ``(lower, upper)`` limits, None for a joint without
    (a continuous one, or one whose ``<limit>`` gives no range)."""
    limit = joint.find("limit")
    if joint.get("type") == "continuous" or limit is None:
        return None
    lower, upper = float(limit.get("lower", 0.0)), float(limit.get("upper", 0.0))
    return (lower, upper) if lower <= upper else None


def _rest_position(joint: ET.Element) -> float:
    """Where a held joint stays unless told: 0, or the middle of its limits when 0 is outside
    them."""
    bounds = _joint_range(joint)
    if bounds is None or bounds[0] <= 0.0 <= bounds[1]:
        return 0.0
    return (bounds[0] + bounds[1]) / 2


def _check_hold(joint: ET.Element, name: str, value: float) -> None:
    """A held position within the joint's limits (a continuous joint takes any)."""
    bounds = _joint_range(joint)
    if bounds is not None and not bounds[0] <= value <= bounds[1]:
        raise LolgpsError(
            f"--hold {name}={value:g}: outside the joint's limits [{bounds[0]:g}, {bounds[1]:g}]"
        )


def _fold_lock_position(joint: ET.Element, kind: str, q: float) -> None:
    """``origin <- origin * motion(q)`` for the held position q of a revolute, continuous or
    prismatic joint: a rotation about, or a translation along, its axis."""
    if q == 0.0:
        return
    axis_el = joint.find("axis")
    axis = np.array(
        [
            float(v)
            for v in (axis_el.get("xyz", "1 0 0") if axis_el is not None else "1 0 0").split()
        ]
    )
    axis = axis / np.linalg.norm(axis)
    origin = joint.find("origin")
    if origin is None:
        origin = ET.SubElement(joint, "origin")
    xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()])
    rotation = _rpy_matrix(*(float(v) for v in origin.get("rpy", "0 0 0").split()))
    if kind == "prismatic":
        xyz = xyz + rotation @ (axis * q)
    else:
        rotation = rotation @ _axis_angle_matrix(axis, q)
    origin.set("xyz", " ".join(repr(float(v)) for v in xyz))
    origin.set("rpy", " ".join(repr(v) for v in _matrix_rpy(rotation)))


def _merge_fixed_leaves(tree: ET.Element, kept: set[str], most: int, path: str) -> None:
    """Where the description has more than ``most`` links, merge links held by fixed joints
    and bearing no other link into their parents, leaves first, until it has no more (or no
    such link is left), sparing the ``kept`` links: each merged link's mass joins its
    parent's at the combined centre of mass, with the inertia about it (parallel axes), and
    its visuals and collisions move to the parent. The arm's dynamics are the same; PyBullet
    keeps the link states of a body of at most :data:`PYBULLET_LINKS` links."""
    links = {link.get("name", ""): link for link in tree.findall("link")}
    if len(links) <= most:
        return
    merged = 0
    while len(links) > most:
        joints = tree.findall("joint")
        parents = {_joint_end(j, "parent") for j in joints}
        leaves = [
            j
            for j in joints
            if j.get("type") == "fixed"
            and _joint_end(j, "child") not in kept
            and _joint_end(j, "child") not in parents
        ]
        if not leaves:
            break
        for joint in reversed(leaves[: len(links) - most]):
            child = links.pop(_joint_end(joint, "child"))
            _merge_link(links[_joint_end(joint, "parent")], child, _transform(joint))
            tree.remove(joint)
            tree.remove(child)
            merged += 1
    warnings.warn(
        f"{path}: {merged} fixed links off the arm merged into their parents (PyBullet keeps "
        f"the states of at most {PYBULLET_LINKS} links)",
        ArmWarning,
        stacklevel=3,
    )


def _joint_end(joint: ET.Element, end: str) -> str:
    element = joint.find(end)
    return "" if element is None else element.get("link", "")


def _transform(element: ET.Element) -> np.ndarray:
    """The 4x4 transform of ``element``'s ``<origin>`` (identity without one)."""
    origin = element.find("origin")
    T = np.eye(4)
    if origin is not None:
        T[:3, :3] = _rpy_matrix(*(float(v) for v in origin.get("rpy", "0 0 0").split()))
        T[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
    return T


def _set_origin(element: ET.Element, T: np.ndarray) -> None:
    origin = element.find("origin")
    if origin is None:
        origin = ET.Element("origin")
        element.insert(0, origin)
    origin.set("xyz", " ".join(repr(float(v)) for v in T[:3, 3]))
    origin.set("rpy", " ".join(repr(v) for v in _matrix_rpy(T[:3, :3])))


def _mass_properties(link: ET.Element, T: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass, centre of mass and inertia about it of ``link``, in the frame ``T`` maps its own
    frame into."""
    inertial = link.find("inertial")
    if inertial is None:
        return 0.0, np.zeros(3), np.zeros((3, 3))
    mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
    mass = float(mass_el.get("value", "0")) if mass_el is not None else 0.0
    inertia = np.zeros((3, 3))
    if inertia_el is not None:
        for key, (i, j) in INERTIA_ENTRIES.items():
            inertia[i, j] = inertia[j, i] = float(inertia_el.get(key, "0"))
    frame = T @ _transform(inertial)
    R = frame[:3, :3]
    return mass, frame[:3, 3], R @ inertia @ R.T


def _merge_link(parent: ET.Element, child: ET.Element, joint: np.ndarray) -> None:
    """``child``, fixed to ``parent`` by a joint at ``joint`` (4x4), merged into ``parent``."""
    m1, c1, I1 = _mass_properties(parent, np.eye(4))
    m2, c2, I2 = _mass_properties(child, joint)
    if m2 > 0.0 or child.find("inertial") is not None:
        mass = m1 + m2
        com = (m1 * c1 + m2 * c2) / mass if mass > 0.0 else c1
        inertia = np.zeros((3, 3))
        for m, c, own in ((m1, c1, I1), (m2, c2, I2)):
            d = c - com
            inertia += own + m * (d @ d * np.eye(3) - np.outer(d, d))
        old = parent.find("inertial")
        if old is not None:
            parent.remove(old)
        add_inertial(parent, com, mass, inertia)
    for kind in ("visual", "collision"):
        for shape in child.findall(kind):
            _set_origin(shape, joint @ _transform(shape))
            parent.append(shape)


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    """URDF's fixed-axis roll-pitch-yaw: ``R = Rz(y) Ry(p) Rx(r)``."""
    cr, sr, cp, sp, cy, sy = (
        math.cos(r),
        math.sin(r),
        math.cos(p),
        math.sin(p),
        math.cos(y),
        math.sin(y),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _matrix_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`_rpy_matrix` (roll 0 at the pitch = +-pi/2 singularity)."""
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(R[2, 0]) > 1 - 1e-12:
        return 0.0, pitch, math.atan2(-R[0, 1], R[1, 1])
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def _axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: ``R = I + sin(a) [k]x + (1 - cos(a)) [k]x^2`` for the unit axis k."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _name_materials(tree: ET.Element) -> None:
    """Name the materials of visuals published with an empty name (``lolgps_material_N``),
    and drop textures without a filename (which name nothing)."""
    for i, material in enumerate(tree.findall("link/visual/material")):
        if not material.get("name"):
            material.set("name", f"lolgps_material_{i}")
    for material in tree.iter("material"):
        for texture in material.findall("texture"):
            if not texture.get("filename"):
                material.remove(texture)


def _portable_text(tree: ET.Element, path: str, package_path: Sequence[str], peg_link: str) -> str:
    """The URDF as text both PyBullet and pytorch-kinematics accept from any folder, and read
    alike: mesh paths resolved to absolute ones (:mod:`.packages`), collision shapes of arm
    links and meshes not found dropped (arm links never collide here; one :class:`ArmWarning`
    names what is missing), transmission/gazebo elements (unused here) dropped, and URDF
    defaults written out where the two readers differ: axis (1, 0, 0) on moving joints that
    omit it (pytorch-kinematics would take (0, 0, 1)), and zero mass and inertia on links
    without ``<inertial>`` (PyBullet would give them 1 kg and 1 kg m^2).  Other tools'
    namespaced extensions (``drake:...``) are dropped, elements and attributes alike,
    materials of visuals published with an empty name are named (``lolgps_material_N``), and
    textures without a filename (which name nothing) dropped."""
    for child in list(tree):
        if child.tag in ("transmission", "gazebo"):
            tree.remove(child)
    _drop_namespaced(tree)
    _name_materials(tree)
    _drop_unused_shapes(tree, path, package_path, peg_link)
    for joint in tree.findall("joint"):
        if joint.get("type") != "fixed" and joint.find("axis") is None:
            ET.SubElement(joint, "axis", xyz="1 0 0")
    for link in tree.findall("link"):
        if link.find("inertial") is None:
            inertial = ET.SubElement(link, "inertial")
            ET.SubElement(inertial, "mass", value="0")
            ET.SubElement(inertial, "inertia", {key: "0" for key in INERTIA_KEYS})
    return ET.tostring(tree, encoding="unicode")


def _drop_namespaced(element: ET.Element) -> None:
    """Remove, below ``element``, every element and attribute in an XML namespace."""
    for key in [k for k in element.attrib if k.startswith("{")]:
        del element.attrib[key]
    for child in list(element):
        if child.tag.startswith("{"):
            element.remove(child)
        else:
            _drop_namespaced(child)


def _drop_unused_shapes(
    tree: ET.Element, path: str, package_path: Sequence[str], peg_link: str
) -> None:
    """Drop the collision shapes of every link but the peg, resolve mesh filenames, and drop
    the shapes whose mesh is not found, or is in a format PyBullet cannot read (it refuses the
    whole URDF for one such mesh); one :class:`ArmWarning` for each kind names the first."""
    missing: list[str] = []
    unreadable: list[str] = []
    for link in tree.findall("link"):
        for element in link.findall("collision") if link.get("name") != peg_link else []:
            link.remove(element)
        for element in [*link.findall("visual"), *link.findall("collision")]:
            mesh = element.find("geometry/mesh")
            if mesh is None:
                continue
            name = mesh.get("filename", "")
            if os.path.splitext(name)[1].lower() not in _MESH_FORMATS:
                unreadable.append(name)
                link.remove(element)
                continue
            resolved = resolve_mesh(name, path, package_path)
            if resolved:
                mesh.set("filename", resolved)
            else:
                missing.append(name)
                link.remove(element)
    if unreadable:
        warnings.warn(
            f"{path}: {len(unreadable)} mesh file(s) in a format PyBullet cannot read, e.g. "
            f"{unreadable[0]!r} (it reads {', '.join(_MESH_FORMATS)}); the arm is loaded "
            f"without them (they are not needed to learn)",
            ArmWarning,
            stacklevel=3,
        )
    if missing:
        warnings.warn(
            f"{path}: {len(missing)} mesh file(s) not found, e.g. {missing[0]!r}; the arm is "
            f"loaded without them (they are not needed to learn; --package-path DIR finds "
            f"their ROS package)",
            ArmWarning,
            stacklevel=3,
        )
