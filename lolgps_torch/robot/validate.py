"""Checks of a URDF's XML against what PyBullet and pytorch-kinematics need, made before either
reads the file: both crash (a traceback, or a segfault for duplicate names) on input they
cannot use.

What is checked, each failure a :class:`LolgpsError` naming the file and the element:

* numbers: finite, and those of geometry and inertia within +-1e6;
* the tree: unique link and joint names, each joint's parent and child defined, one root
  link, every link reachable from it (no cycles);
* joints: a known type; at most one of each part (``<origin>``, ``<axis>``, ``<limit>``...);
  finite numbers; a non-zero axis on moving joints; revolute and prismatic joints carry a
  ``<limit>``; a ``<limit>`` has ``effort > 0`` and ``velocity >= 0`` (both required), and
  ``lower < upper``; damping and friction are ``>= 0``;
* inertia: any ``<inertial>`` holds exactly one ``<mass>`` (finite, ``>= 0``) and one
  ``<inertia>`` with its six finite entries forming a positive semi-definite matrix.  A
  *driven* link (the child of a non-fixed joint) must have one, with positive mass and a
  positive-definite matrix, or the joint-space mass matrix is singular.  Links fixed to a
  driven link may be massless (pybullet_data's Panda has two such links).  The triangle
  inequality of the principal moments is not required: pybullet_data's xArm 6 breaks it by
  13 % and simulates well;
* materials: a name and, for a colour, four rgba numbers (pytorch-kinematics' parser
  stops without them);
* shapes: each ``<visual>``/``<collision>`` has one ``<geometry>`` with exactly one shape of
  positive finite size; a mesh's file exists (see :func:`resolve_mesh`).
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

import numpy as np

from lolgps_torch.errors import LolgpsError

_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")
_LIMITED = ("revolute", "prismatic")
# a joint's optional parts: (required, optional) numeric attributes
_JOINT_PARTS = {
    "dynamics": ((), ("damping", "friction")),
    "calibration": ((), ("rising", "falling")),
    "safety_controller": (("k_velocity",), ("k_position", "soft_lower_limit", "soft_upper_limit")),
    "mimic": ((), ("multiplier", "offset")),
}
# Geometry and inertia numbers beyond this (m, rad, kg, kg m^2) overflow in the kinematics'
# float32 parse or its squares; limits, damping and the like are left unbounded.
_LARGEST = 1e6
_BOUNDED = ("origin", "axis", "mass", "inertia", "box", "cylinder", "capsule", "sphere", "mesh")
_INERTIA = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
# each primitive shape's size attributes and how many numbers each holds
_SHAPES = {
    "box": (("size", 3),),
    "cylinder": (("radius", 1), ("length", 1)),
    "capsule": (("radius", 1), ("length", 1)),
    "sphere": (("radius", 1),),
}


def validate_urdf(robot: ET.Element, path: str) -> str:
    """Check a parsed URDF (see the module docstring); return its root link's name.

    :param robot: the XML tree's root element.
    :param path: the URDF file, for the messages and to resolve mesh paths.
    """
    if robot.tag != "robot":
        raise LolgpsError(f"{path}: the root element is <{robot.tag}>, not <robot>")
    links = _named(robot, "link", path)
    joints = _named(robot, "joint", path)
    parents = _tree_edges(links, joints, path)
    root = _single_root(links, parents, path)
    for name, joint in joints.items():
        _check_joint(joint, f"{path}: joint {name!r}")
    driven = {
        child for child, (_, joint) in parents.items() if joints[joint].get("type") != "fixed"
    }
    for material in robot.findall("material"):
        label = material.get("name")
        _check_material(material, f"{path}: material {label!r}" if label else path)
    base_dir = os.path.dirname(os.path.abspath(path))
    for name, link in links.items():
        where = f"{path}: link {name!r}"
        _check_inertial(link, where, driven=name in driven)
        _check_shapes(link, where, base_dir)
    return root


def resolve_mesh(name: str, base_dir: str) -> str | None:
    """Absolute path of a mesh file, or None if it is not found.

    ``package://pkg/rest`` is looked up as ``pkg/rest`` and ``rest`` in the URDF's folder and
    its parent; ``file://`` and absolute paths are taken as they are; relative paths are
    looked up in the URDF's folder and its parent.
    """
    if name.startswith("package://"):
        rest = name[len("package://") :]
        candidates = [rest, rest.split("/", 1)[-1]]  # with and without a ROS package name
    elif name.startswith("file://"):
        candidates = [name[len("file://") :]]
    elif "://" in name or not name:
        return None
    else:
        candidates = [name]
    for candidate in candidates:
        for folder in (base_dir, os.path.dirname(base_dir)):
            full = os.path.join(folder, candidate)  # an absolute candidate ignores the folder
            if os.path.isfile(full):
                return full
    return None


def _named(robot: ET.Element, tag: str, path: str) -> dict[str, ET.Element]:
    """The robot's ``<link>`` or ``<joint>`` elements by name; names must exist and be unique."""
    elements: dict[str, ET.Element] = {}
    for element in robot.findall(tag):
        name = element.get("name")
        if not name:
            raise LolgpsError(f"{path}: a <{tag}> has no name")
        if name in elements:
            raise LolgpsError(f"{path}: {tag} name {name!r} is used twice")
        elements[name] = element
    return elements


def _tree_edges(
    links: dict[str, ET.Element], joints: dict[str, ET.Element], path: str
) -> dict[str, tuple[str, str]]:
    """``child link -> (parent link, joint)``; each link is the child of at most one joint."""
    parents: dict[str, tuple[str, str]] = {}
    for name, joint in joints.items():
        where = f"{path}: joint {name!r}"
        parent, child = (_link_ref(joint, end, where) for end in ("parent", "child"))
        for end, link in (("parent", parent), ("child", child)):
            if link not in links:
                raise LolgpsError(f"{where}: {end} link {link!r} is not defined")
        if child in parents:
            raise LolgpsError(
                f"{path}: link {child!r} is the child of two joints, {parents[child][1]!r} and {name!r}"
            )
        parents[child] = (parent, name)
    return parents


def _link_ref(joint: ET.Element, end: str, where: str) -> str:
    link = _child(joint, end, where).get("link")
    if not link:
        raise LolgpsError(f"{where}: <{end}> has no link attribute")
    return link


def _single_root(
    links: dict[str, ET.Element], parents: dict[str, tuple[str, str]], path: str
) -> str:
    """The one link without a parent joint; every other link must hang below it."""
    roots = [name for name in links if name not in parents]
    if len(roots) != 1:
        raise LolgpsError(f"{path}: URDF must have exactly one root link, found {roots}")
    children: dict[str, list[str]] = {}
    for child, (parent, _) in parents.items():
        children.setdefault(parent, []).append(child)
    reached, frontier = {roots[0]}, [roots[0]]
    while frontier:
        below = children.get(frontier.pop(), [])
        reached.update(below)
        frontier.extend(below)
    cut_off = [name for name in links if name not in reached]
    if cut_off:
        raise LolgpsError(f"{path}: joints form a cycle through links {cut_off}")
    return roots[0]


def _check_joint(joint: ET.Element, where: str) -> None:
    """Type, origin, axis, limits and the optional parts of one joint."""
    kind = joint.get("type")
    if kind not in _JOINT_TYPES:
        raise LolgpsError(f"{where}: unknown joint type {kind!r}")
    _check_origin(_optional_child(joint, "origin", where), where)
    axis = _optional_child(joint, "axis", where)
    xyz = _required_numbers(axis, "xyz", where, 3) if axis is not None else (1.0, 0.0, 0.0)
    if kind != "fixed" and math.hypot(*xyz) < 1e-6:
        raise LolgpsError(f"{where}: <axis> xyz is (nearly) the zero vector")
    _check_limit(joint, kind, where)
    for tag, (required, optional) in _JOINT_PARTS.items():
        part = _optional_child(joint, tag, where)
        if part is None:
            continue
        for attr in required:
            _required_numbers(part, attr, where, 1)
        for attr in optional:
            value = _number(part, attr, where)
            if tag == "dynamics" and value is not None and value < 0:
                raise LolgpsError(f"{where}: <dynamics> {attr} must not be negative, got {value}")
    mimic = joint.find("mimic")
    if mimic is not None and not mimic.get("joint"):
        raise LolgpsError(f"{where}: <mimic> has no joint attribute")


def _check_limit(joint: ET.Element, kind: str, where: str) -> None:
    """Effort and velocity (both required, as pytorch-kinematics' parser insists), and
    ``lower < upper`` on revolute and prismatic joints."""
    limit = _optional_child(joint, "limit", where)
    if limit is None:
        if kind in _LIMITED:
            raise LolgpsError(f"{where}: a {kind} joint needs a <limit>")
        return
    effort, velocity = (_required_numbers(limit, a, where, 1)[0] for a in ("effort", "velocity"))
    lower, upper = (_number(limit, attr, where) for attr in ("lower", "upper"))
    if kind in _LIMITED and lower is not None and upper is not None and not lower < upper:
        raise LolgpsError(f"{where}: <limit> lower {lower} is not below upper {upper}")
    if effort <= 0:
        raise LolgpsError(f"{where}: <limit> effort must be positive, got {effort}")
    if velocity < 0:
        raise LolgpsError(f"{where}: <limit> velocity must not be negative, got {velocity}")


def _check_material(material: ET.Element, where: str) -> None:
    """A name (pytorch-kinematics' parser needs one), and an rgba colour of four numbers."""
    if not material.get("name"):
        raise LolgpsError(f"{where}: <material> has no name")
    color = _optional_child(material, "color", where)
    if color is not None:
        _required_numbers(color, "rgba", where, 4)
    texture = _optional_child(material, "texture", where)
    if texture is not None and not texture.get("filename"):
        raise LolgpsError(f"{where}: <texture> has no filename")


def _check_inertial(link: ET.Element, where: str, driven: bool) -> None:
    """Mass and inertia; a driven link needs both, positive (see the module docstring)."""
    moves = "the link moves with its parent joint"
    inertial = _optional_child(link, "inertial", where)
    if inertial is None:
        if driven:
            raise LolgpsError(f"{where}: <inertial> missing ({moves})")
        return
    here = f"{where}: <inertial>"
    _check_origin(_optional_child(inertial, "origin", here), here)
    mass = _required_numbers(_child(inertial, "mass", here), "value", here, 1)[0]
    element = _child(inertial, "inertia", here)
    xx, xy, xz, yy, yz, zz = (_required_numbers(element, a, here, 1)[0] for a in _INERTIA)
    smallest = float(np.linalg.eigvalsh(np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]))[0])
    if mass < 0:
        raise LolgpsError(f"{where}: mass must not be negative, got {mass}")
    if driven and mass == 0:
        raise LolgpsError(f"{where}: mass must be positive ({moves}), got {mass}")
    if driven and smallest <= 0:
        raise LolgpsError(f"{where}: inertia is not positive definite ({moves})")
    if smallest < -1e-9 * max(abs(xx), abs(yy), abs(zz)):
        raise LolgpsError(f"{where}: inertia is not positive semi-definite")


def _check_shapes(link: ET.Element, where: str, base_dir: str) -> None:
    """One sized shape per ``<visual>``/``<collision>`` geometry; mesh files present."""
    for kind in ("visual", "collision"):
        for element in link.findall(kind):
            here = f"{where}: <{kind}>"
            _check_origin(_optional_child(element, "origin", here), here)
            material = _optional_child(element, "material", here)
            if material is not None:
                _check_material(material, here)
            shapes = list(_child(element, "geometry", here))
            if len(shapes) != 1:
                tags = ", ".join(f"<{s.tag}>" for s in shapes) or "none"
                raise LolgpsError(f"{here}: <geometry> needs exactly one shape, found {tags}")
            _check_shape(shapes[0], here, base_dir)


def _check_shape(shape: ET.Element, where: str, base_dir: str) -> None:
    if shape.tag == "mesh":
        filename = shape.get("filename", "")
        if resolve_mesh(filename, base_dir) is None:
            raise LolgpsError(f"{where}: mesh file {filename!r} not found")
        scale = _numbers(shape, "scale", where, 3)
        if scale is not None and not all(scale):
            raise LolgpsError(f"{where}: <mesh> scale has a zero entry")
        return
    if shape.tag not in _SHAPES:
        raise LolgpsError(f"{where}: unknown geometry <{shape.tag}>")
    for attr, count in _SHAPES[shape.tag]:
        if min(_required_numbers(shape, attr, where, count)) <= 0:
            raise LolgpsError(f"{where}: <{shape.tag}> {attr} must be positive")


def _check_origin(origin: ET.Element | None, where: str) -> None:
    if origin is not None:
        for attr in ("xyz", "rpy"):
            _numbers(origin, attr, where, 3)


def _optional_child(parent: ET.Element, tag: str, where: str) -> ET.Element | None:
    """The one ``<tag>`` child of ``parent``, or None if there is none."""
    found = parent.findall(tag)
    if len(found) > 1:
        raise LolgpsError(f"{where}: more than one <{tag}>")
    return found[0] if found else None


def _child(parent: ET.Element, tag: str, where: str) -> ET.Element:
    """The one ``<tag>`` child of ``parent``, which must be there."""
    found = _optional_child(parent, tag, where)
    if found is None:
        raise LolgpsError(f"{where}: <{tag}> missing")
    return found


def _number(element: ET.Element, attr: str, where: str) -> float | None:
    values = _numbers(element, attr, where, 1)
    return values[0] if values is not None else None


def _required_numbers(element: ET.Element, attr: str, where: str, count: int) -> tuple[float, ...]:
    values = _numbers(element, attr, where, count)
    if values is None:
        raise LolgpsError(f"{where}: <{element.tag}> has no {attr} attribute")
    return values


def _numbers(element: ET.Element, attr: str, where: str, count: int) -> tuple[float, ...] | None:
    """``count`` finite numbers from a space-separated attribute; None if it is absent."""
    text = element.get(attr)
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        raise LolgpsError(f"{where}: <{element.tag}> {attr}={text!r} is not a number") from None
    if len(values) != count:
        raise LolgpsError(
            f"{where}: <{element.tag}> {attr}={text!r} needs {count} number(s), got {len(values)}"
        )
    if not all(math.isfinite(v) for v in values):
        raise LolgpsError(f"{where}: <{element.tag}> {attr}={text!r} is not finite")
    if element.tag in _BOUNDED and max(abs(v) for v in values) > _LARGEST:
        raise LolgpsError(f"{where}: <{element.tag}> {attr}={text!r} is beyond +-{_LARGEST:g}")
    return values
