"""The URDF's XML edited into the arm's description: the joints off the arm held fixed where
they stand (:func:`lock_joints`), fixed leaf links merged into their parents where PyBullet
would keep too many (:func:`merge_fixed_leaves`), and the text that PyBullet and
pytorch-kinematics both accept from any folder and read alike (:func:`portable_text`)."""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Sequence

import numpy as np

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.packages import resolve_mesh
from lolgps_torch.robot.spec import INERTIA_ENTRIES, INERTIA_KEYS, add_inertial
from lolgps_torch.robot.validate import ArmWarning

_HELD = ("revolute", "continuous", "prismatic")  # the moving joints a position can be held at
PYBULLET_LINKS = 128  # PyBullet keeps the link states of a body of at most so many links
# mesh file extensions PyBullet reads (any case)
_MESH_FORMATS = (".stl", ".obj", ".dae", ".cdf", ".vtk")


def lock_joints(
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


def merge_fixed_leaves(tree: ET.Element, kept: set[str], most: int, path: str) -> None:
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


def portable_text(tree: ET.Element, path: str, package_path: Sequence[str], peg_link: str) -> str:
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
