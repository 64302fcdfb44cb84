"""What the method needs to know about a URDF arm, read once with yourdfpy after the XML has
been checked against what PyBullet and pytorch-kinematics need (:mod:`.validate`).

yourdfpy (and trimesh, which it imports) is imported only when a URDF is parsed, so processes
that merely receive an :class:`ArmSpec` (the evaluation's workers) do not pay for it.

An :class:`ArmSpec` is the single description that drives both PyBullet (joint names are
mapped to body joint indices) and pytorch-kinematics (the serial chain to the point
frame), so the two cannot disagree.

The peg.  Every arm ends in a *point frame* whose origin is the peg tip and whose +z axis
points out along the peg.  A URDF that carries its own peg names that frame ``peg_tip``
(its parent link is the peg's collision body).  Otherwise a peg of the configured length
and radius is attached to the end-effector link along ``PegConfig.axis``: the URDF text
is extended with two fixed links (``lolgps_peg`` and ``lolgps_peg_tip``).  The two
end-effector points of the state are the tip, ``(0, 0, 0)``, and the top,
``(0, 0, -point_separation)``, in the point frame.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.validate import resolve_mesh, validate_urdf

if TYPE_CHECKING:
    import yourdfpy

CARRIED_PEG_TIP = "peg_tip"
ATTACHED_PEG = "lolgps_peg"
ATTACHED_PEG_TIP = "lolgps_peg_tip"
_ACTUATED = ("revolute", "continuous")
_INERTIA_KEYS = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
# rpy that turns the point frame's +z onto each supported peg axis of the end-effector link.
_AXIS_RPY = {
    "x": (0.0, math.pi / 2, 0.0),
    "-x": (0.0, -math.pi / 2, 0.0),
    "y": (-math.pi / 2, 0.0, 0.0),
    "-y": (math.pi / 2, 0.0, 0.0),
    "z": (0.0, 0.0, 0.0),
    "-z": (math.pi, 0.0, 0.0),
}


@dataclass(frozen=True)
class PegConfig:
    """The peg attached to arms whose URDF has none (m), and the end-effector point spacing.

    :param length: peg length along ``axis`` from the end-effector link origin.
    :param radius: peg radius.
    :param axis: the end-effector link axis the peg points along: x, y, z, -x, -y or -z.
    :param point_separation: distance from the tip to the second (top) point on the axis.
    """

    length: float = 0.20
    radius: float = 0.015
    axis: str = "z"
    point_separation: float = 0.15


@dataclass(frozen=True)
class ArmSpec:
    """A URDF arm as the method sees it.

    :param urdf_text: URDF text used by both simulator and kinematics (peg attached if needed,
        relative mesh paths made absolute).
    :param source_path: the URDF file given by the user.
    :param source_sha256: SHA-256 of that file's bytes.
    :param root_link: the URDF's root link (the simulator's base, fixed in the world).
    :param ee_link: the end-effector link (the peg is fixed to it).
    :param point_link: the point frame; its origin is the peg tip and +z runs along the peg.
    :param peg_link: the link whose collision shape is the peg (the only part touching the world).
    :param joint_names: actuated joints from base to end effector (the action order).
    :param lower: joint lower limits (rad). :param upper: joint upper limits (rad).
    :param effort: torque limits (N m). :param velocity: velocity limits (rad/s).
    :param point_offsets: the tip and top points in the point frame, ``((x, y, z), (x, y, z))``.
    :param peg_radius: peg radius (m), from the URDF or the attached peg.
    """

    urdf_text: str
    source_path: str
    source_sha256: str
    root_link: str
    ee_link: str
    point_link: str
    peg_link: str
    joint_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    effort: tuple[float, ...]
    velocity: tuple[float, ...]
    point_offsets: tuple[tuple[float, float, float], tuple[float, float, float]]
    peg_radius: float

    @property
    def dof(self) -> int:
        return len(self.joint_names)


def load_arm(path: str, ee_link: str | None = None, peg: PegConfig | None = None) -> ArmSpec:
    """Read and validate a URDF arm; raise :class:`LolgpsError` with a one-line reason."""
    peg = peg or PegConfig()
    if peg.axis not in _AXIS_RPY:
        raise LolgpsError(f"--peg-axis must be one of {', '.join(_AXIS_RPY)}, got {peg.axis!r}")
    raw, tree, robot, root = _parse(path)
    parent_joint = {j.child: j for j in robot.robot.joints}
    links = [link.name for link in robot.robot.links]

    def path_joints(link: str) -> list[yourdfpy.Joint]:
        chain = []
        while link in parent_joint:
            joint = parent_joint[link]
            chain.append(joint)
            link = joint.parent
        return chain[::-1]

    if not any(j.type in _ACTUATED for j in robot.robot.joints):
        raise LolgpsError(f"{path}: URDF has no revolute or continuous joints to actuate")
    if ee_link is None:
        ee_link = _detect_ee_link(links, path_joints)
    elif ee_link not in links:
        raise LolgpsError(f"unknown end-effector link {ee_link!r}; links are: {', '.join(links)}")
    actuated = _actuated_joints(path_joints(ee_link), ee_link)

    text = _portable_text(tree, os.path.dirname(os.path.abspath(path)))
    carries_peg = CARRIED_PEG_TIP in links and ee_link == CARRIED_PEG_TIP
    if carries_peg:
        point_link, peg_link = CARRIED_PEG_TIP, parent_joint[CARRIED_PEG_TIP].parent
        peg_radius = _cylinder_radius(robot, peg_link, path)
    else:
        if ATTACHED_PEG in links:
            raise LolgpsError(
                f"{path}: link name {ATTACHED_PEG!r} is reserved for the attached peg"
            )
        text = _attach_peg(text, ee_link, peg)
        point_link, peg_link, peg_radius = ATTACHED_PEG_TIP, ATTACHED_PEG, peg.radius

    lims = [_limits(j, path) for j in actuated]
    return ArmSpec(
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
    )


def _parse(path: str) -> tuple[bytes, ET.Element, yourdfpy.URDF, str]:
    """The file's bytes, its XML tree, yourdfpy's model and the root link; one-line errors for
    bad files, raised before yourdfpy, pytorch-kinematics or PyBullet read them."""
    import yourdfpy  # here, not at the top: see the module docstring

    if not os.path.isfile(path):
        raise LolgpsError(f"URDF not found: {path}")
    with open(path, "rb") as fh:
        raw = fh.read()
    text = raw.decode("utf-8", errors="replace")
    if "<!ENTITY" in text:
        raise LolgpsError(f"{path}: URDF declares XML entities; they are not resolved")
    try:
        tree = ET.fromstring(text)
    except ET.ParseError as exc:
        raise LolgpsError(f"{path}: malformed XML ({exc})") from None
    root = validate_urdf(tree, path)
    try:
        robot = yourdfpy.URDF.load(
            io.BytesIO(raw), build_scene_graph=False, load_meshes=False, load_collision_meshes=False
        )
    except Exception as exc:  # yourdfpy raises assorted types on schema errors
        raise LolgpsError(f"{path}: not a valid URDF ({type(exc).__name__}: {exc})") from None
    return raw, tree, robot, root


def _actuated_joints(chain: list[yourdfpy.Joint], ee_link: str) -> list[yourdfpy.Joint]:
    """The actuated joints of the chain from the root to ``ee_link``."""
    actuated = [j for j in chain if j.type in _ACTUATED]
    if not actuated:
        raise LolgpsError(f"end-effector link {ee_link!r} is not downstream of any actuated joint")
    unsupported = [j for j in chain if j.type not in (*_ACTUATED, "fixed")]
    if unsupported:
        raise LolgpsError(
            f"joint {unsupported[0].name!r} ({unsupported[0].type}) lies on the chain to "
            f"{ee_link!r}; only revolute, continuous and fixed joints are supported there"
        )
    return actuated


def _limits(j: yourdfpy.Joint, path: str) -> tuple[float, float, float, float]:
    """(lower, upper, effort, velocity); continuous joints get [-pi, pi] for placement."""
    lim = j.limit
    if lim is None or lim.effort is None:
        raise LolgpsError(f"{path}: joint {j.name!r} has no effort limit")
    if j.type == "continuous" or lim.lower is None or lim.upper is None:
        lower, upper = -math.pi, math.pi
    else:
        lower, upper = float(lim.lower), float(lim.upper)
    velocity = float(lim.velocity) if lim.velocity else 10.0
    return lower, upper, float(lim.effort), velocity


def _detect_ee_link(links: list[str], path_joints: Callable[[str], list[yourdfpy.Joint]]) -> str:
    """End of the longest actuated chain: most revolute joints, then fixed-only tail, then depth."""

    def rank(link: str) -> tuple[int, int, int]:
        chain = path_joints(link)
        n_act = sum(j.type in _ACTUATED for j in chain)
        last = max((i for i, j in enumerate(chain) if j.type in _ACTUATED), default=-1)
        fixed_tail = all(j.type == "fixed" for j in chain[last + 1 :])
        return n_act, int(fixed_tail), len(chain)

    return max(links, key=rank)


def _cylinder_radius(robot: yourdfpy.URDF, link: str, path: str) -> float:
    for collision in robot.link_map[link].collisions:
        if collision.geometry.cylinder is not None:
            return float(collision.geometry.cylinder.radius)
    raise LolgpsError(f"{path}: peg link {link!r} (parent of {CARRIED_PEG_TIP!r}) has no cylinder")


def _portable_text(tree: ET.Element, base_dir: str) -> str:
    """The URDF as text both PyBullet and pytorch-kinematics accept from any folder, and read
    alike: mesh paths resolved to absolute ones, transmission/gazebo elements (unused here)
    dropped, and URDF defaults written out where the two readers differ: axis (1, 0, 0) on
    moving joints that omit it (pytorch-kinematics would take (0, 0, 1)), and zero mass and
    inertia on links without ``<inertial>`` (PyBullet would give them 1 kg and 1 kg m^2)."""
    for child in list(tree):
        if child.tag in ("transmission", "gazebo"):
            tree.remove(child)
    for mesh in tree.iter("mesh"):
        resolved = resolve_mesh(mesh.get("filename", ""), base_dir)
        if resolved:
            mesh.set("filename", resolved)
    for joint in tree.findall("joint"):
        if joint.get("type") != "fixed" and joint.find("axis") is None:
            ET.SubElement(joint, "axis", xyz="1 0 0")
    for link in tree.findall("link"):
        if link.find("inertial") is None:
            inertial = ET.SubElement(link, "inertial")
            ET.SubElement(inertial, "mass", value="0")
            ET.SubElement(inertial, "inertia", {key: "0" for key in _INERTIA_KEYS})
    return ET.tostring(tree, encoding="unicode")


def _attach_peg(text: str, ee_link: str, peg: PegConfig) -> str:
    """Append a peg cylinder and its tip frame, fixed to ``ee_link`` along ``peg.axis``."""
    r, p, y = _AXIS_RPY[peg.axis]
    half = peg.length / 2
    inertia = 0.2 * (3 * peg.radius**2 + peg.length**2) / 12
    xml = f"""
  <link name="{ATTACHED_PEG}">
    <inertial><origin xyz="0 0 {half}"/><mass value="0.2"/>
      <inertia ixx="{inertia}" iyy="{inertia}" izz="{0.1 * peg.radius**2}" ixy="0" ixz="0" iyz="0"/>
    </inertial>
    <visual><origin xyz="0 0 {half}"/>
      <geometry><cylinder radius="{peg.radius}" length="{peg.length}"/></geometry></visual>
    <collision><origin xyz="0 0 {half}"/>
      <geometry><cylinder radius="{peg.radius}" length="{peg.length}"/></geometry></collision>
  </link>
  <joint name="{ATTACHED_PEG}_joint" type="fixed">
    <parent link="{ee_link}"/><child link="{ATTACHED_PEG}"/><origin rpy="{r} {p} {y}"/>
  </joint>
  <link name="{ATTACHED_PEG_TIP}">
    <inertial><mass value="0.001"/>
      <inertia ixx="1e-6" iyy="1e-6" izz="1e-6" ixy="0" ixz="0" iyz="0"/></inertial>
  </link>
  <joint name="{ATTACHED_PEG_TIP}_joint" type="fixed">
    <parent link="{ATTACHED_PEG}"/><child link="{ATTACHED_PEG_TIP}"/>
    <origin xyz="0 0 {peg.length}"/>
  </joint>
"""
    end = text.rfind("</robot>")
    return text[:end] + xml + text[end:]
