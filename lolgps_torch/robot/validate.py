"""Checks of a URDF's XML against what PyBullet and pytorch-kinematics need, made before either
reads the file: both crash (a traceback, or a segfault for duplicate names) on input they
cannot use.

What is checked, each failure a :class:`LolgpsError` naming the file and the element:

* numbers: finite, and those of geometry and inertia within +-1e6;
* the tree: unique link and joint names, each joint's parent and child defined, one root
  link, every link reachable from it (no cycles);
* joints: a known type; at most one of each part (``<origin>``, ``<axis>``, ``<limit>``...);
  finite numbers; a non-zero axis on moving joints; damping and friction are ``>= 0``.  The
  ``<limit>`` of a joint the method actuates is checked by :func:`check_actuated_limit`
  (``effort >= 0``, 0 or none taken as unknown, ``velocity >= 0``, ``lower < upper``); other
  joints are locked or fixed,
  and their limits mean nothing here (published descriptions put placeholders there);
* inertia: any ``<inertial>`` holds exactly one ``<mass>`` (finite, ``>= 0``) and one
  ``<inertia>`` with six finite entries forming a positive semi-definite matrix (a principal
  moment of 0 is a thin rod's, and physical; a negative one within rounding, 1e-9 of the
  largest diagonal entry plus :data:`INERTIA_ROUNDING`, is taken as 0: iCub's published
  head has ``ixz = 2.4e-35`` and nothing else).  A link without ``<inertial>`` is massless (the
  URDF default), as is one of mass 0, moving or not: once the arm is assembled (joints locked,
  peg attached) :func:`check_moved_mass` refuses only an actuated joint that moves no mass at
  all, and warns about the massless links that actuated joints drive.  Principal moments that break the triangle
  inequality ``I1 + I2 >= I3`` cannot belong to a rigid body but simulate well (pybullet_data's
  xArm 6 breaks it by 13 %): they are warned about (:class:`ArmWarning`), as is a driven link
  whose inertia is entirely zero;
* materials: a name and, for a colour, four rgba numbers (pytorch-kinematics' parser
  stops without them); a visual's material may have an empty name (xacro writes
  ``name=""``), which the loader replaces;
* shapes: each ``<visual>``/``<collision>`` has one ``<geometry>`` with exactly one shape of
  positive finite size; a mesh names a file (whether it exists is the loader's concern: a
  missing one is only a warning, since arm meshes are never needed here).
"""

from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET

import numpy as np

from lolgps_torch.errors import LolgpsError

_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar")
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
INERTIA_ROUNDING = 1e-12  # kg m^2: far below any physical part (a 1 g bead of 1 mm: 4e-10)
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
    static = _welded_to(root, parents, joints)
    for material in robot.findall("material"):
        label = material.get("name")
        _check_material(material, f"{path}: material {label!r}" if label else path, top_level=True)
    suspect = []
    for name, link in links.items():
        where = f"{path}: link {name!r}"
        suspect += _check_inertial(link, where, name, name in driven, name in static)
        _check_shapes(link, where)
    if suspect:
        warnings.warn(
            f"{path}: suspect inertia (kept as published): {'; '.join(suspect)}",
            ArmWarning,
            stacklevel=2,
        )
    return root


class ArmWarning(UserWarning):
    """Something in an arm description that is legal but suspect, or unused and missing
    (scripts print it as one ``warning:`` line)."""


def _check_limit_numbers(joint: ET.Element, kind: str, where: str) -> None:
    """A moving joint's ``<limit>`` numbers are numbers (a fixed joint's are ignored)."""
    limit = _optional_child(joint, "limit", where)
    if limit is not None and kind != "fixed":
        for attr in ("lower", "upper", "effort", "velocity"):
            _number(limit, attr, where)


def check_actuated_limit(joint: ET.Element, where: str) -> bool:
    """The ``<limit>`` of a joint the method actuates, as ROS's URDF parser reads it: a revolute
    joint needs one, a continuous joint may go without (then its effort is unknown); a given
    ``<limit>`` has a velocity (ROS's parser and pytorch-kinematics' insist), ``effort >= 0``,
    ``velocity >= 0`` and, on a revolute joint, ``lower < upper``.  Returns whether the effort
    is unknown: 0 or absent (ROS-Industrial publishes 0 as a placeholder; the loader derives a
    limit, :mod:`.effort`)."""
    kind = joint.get("type")
    limit = _optional_child(joint, "limit", where)
    if limit is None:
        if kind == "continuous":
            return True
        raise LolgpsError(
            f"{where}: a revolute joint needs a <limit lower=... upper=... effort=... "
            f"velocity=...>; add one"
        )
    if limit.get("velocity") is None:
        raise LolgpsError(
            f'{where}: <limit> has no velocity attribute (ROS requires one too); add velocity="..."'
            f" with the joint's top speed (rad/s)"
        )
    effort = _number(limit, "effort", where) or 0.0
    velocity = _required_numbers(limit, "velocity", where, 1)[0]
    lower, upper = (_number(limit, attr, where) for attr in ("lower", "upper"))
    if kind == "revolute" and lower is not None and upper is not None and not lower < upper:
        raise LolgpsError(
            f"{where}: <limit> lower {lower} is not below upper {upper}; widen the range, or "
            f"pick another --ee-link so that this joint is locked"
        )
    if effort < 0:
        raise LolgpsError(
            f"{where}: <limit> effort must not be negative, got {effort}; set the joint's "
            f"torque limit (or 0 to have one derived from the arm)"
        )
    if velocity < 0:
        raise LolgpsError(f"{where}: <limit> velocity must not be negative, got {velocity}")
    return effort == 0


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
    _check_limit_numbers(joint, kind, where)
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


def _check_material(material: ET.Element, where: str, top_level: bool) -> None:
    """A name (pytorch-kinematics' parser needs one; as in ROS's parser a visual's material
    may name itself ``""``, as xacro output does, and the loader replaces that), and an rgba
    colour of four numbers.  A ``<texture>`` without a filename is accepted, as ROS's parser
    accepts it (the loader drops it)."""
    name = material.get("name")
    if name is None or (top_level and not name):
        raise LolgpsError(f"{where}: <material> has no name")
    color = _optional_child(material, "color", where)
    if color is not None:
        _required_numbers(color, "rgba", where, 4)
    _optional_child(material, "texture", where)


def _welded_to(
    root: str, parents: dict[str, tuple[str, str]], joints: dict[str, ET.Element]
) -> set[str]:
    """The links fixed to the root through fixed joints alone: they never move."""
    welded = {root}
    changed = True
    while changed:
        changed = False
        for child, (parent, joint) in parents.items():
            if child not in welded and parent in welded and joints[joint].get("type") == "fixed":
                welded.add(child)
                changed = True
    return welded


def _check_inertial(
    link: ET.Element, where: str, name: str, driven: bool, static: bool
) -> list[str]:
    """Mass and inertia (see the module docstring); returns what is suspect, for a warning.
    The inertia of a link welded to the fixed base never matters: there a matrix that is not
    positive semi-definite is only suspect."""
    inertial = _optional_child(link, "inertial", where)
    if inertial is None:
        return []  # massless (the URDF default); see check_moved_mass
    here = f"{where}: <inertial>"
    _check_origin(_optional_child(inertial, "origin", here), here)
    mass = _required_numbers(_child(inertial, "mass", here), "value", here, 1)[0]
    element = _child(inertial, "inertia", here)
    xx, xy, xz, yy, yz, zz = (_required_numbers(element, a, here, 1)[0] for a in _INERTIA)
    moments = np.linalg.eigvalsh(np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]))
    scale = max(abs(xx), abs(yy), abs(zz))
    if mass < 0:
        raise LolgpsError(f"{where}: mass must not be negative, got {mass}")
    rounding = 1e-9 * scale + INERTIA_ROUNDING
    if moments[0] < -rounding and static:
        return [f"{name!r} (on the fixed base) inertia is not positive semi-definite"]
    if moments[0] < -rounding:
        raise LolgpsError(
            f"{where}: inertia is not positive semi-definite (principal moments "
            f"{', '.join(f'{m:.3g}' for m in moments)}); correct ixx..izz"
        )
    if moments[0] + moments[1] < moments[2] * (1 - 1e-6) - INERTIA_ROUNDING:
        return [
            f"{name!r} principal moments break I1 + I2 >= I3 by {moments[2] - moments[0] - moments[1]:.2g}"
        ]
    if driven and scale == 0 and mass > 0:
        return [f"{name!r} (driven) has zero inertia"]
    return []


def _check_shapes(link: ET.Element, where: str) -> None:
    """One sized shape per ``<visual>``/``<collision>`` geometry; a mesh names its file."""
    for kind in ("visual", "collision"):
        for element in link.findall(kind):
            here = f"{where}: <{kind}>"
            _check_origin(_optional_child(element, "origin", here), here)
            material = _optional_child(element, "material", here)
            if material is not None:
                _check_material(material, here, top_level=False)
            shapes = list(_child(element, "geometry", here))
            if len(shapes) != 1:
                tags = ", ".join(f"<{s.tag}>" for s in shapes) or "none"
                raise LolgpsError(f"{here}: <geometry> needs exactly one shape, found {tags}")
            _check_shape(shapes[0], here)


def _check_shape(shape: ET.Element, where: str) -> None:
    if shape.tag == "mesh":
        if not shape.get("filename"):
            raise LolgpsError(f"{where}: <mesh> has no filename")
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


def check_moved_mass(text: str, path: str) -> list[str]:
    """Each moving joint of the assembled arm's URDF ``text`` (joints locked, peg attached)
    moves some mass: refuse, naming the joint, one whose whole subtree is massless (its
    motion would have no inertia), and refuse a kinematic-only description, in which no link
    that a moving joint drives has mass (the arm would move as the peg alone: on the IRB 140
    of rtb-data every local controller diverged, 0/8); one :class:`ArmWarning` names the
    massless links that moving joints drive (no ``<inertial>``, the URDF default, or mass 0),
    and is returned.

    :param text: the URDF handed to PyBullet and the dynamics model.
    :param path: the source file, for the messages.
    """
    robot = ET.fromstring(text)
    mass = {}
    for link in robot.findall("link"):
        element = link.find("inertial/mass")
        mass[link.get("name", "")] = (
            float(element.get("value", "0")) if element is not None else 0.0
        )
    children: dict[str, list[str]] = {}
    moving = []
    for joint in robot.findall("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            continue
        children.setdefault(parent.get("link", ""), []).append(child.get("link", ""))
        if joint.get("type") != "fixed":
            moving.append((joint.get("name", ""), child.get("link", "")))

    def moved(link: str) -> float:
        return mass.get(link, 0.0) + sum(moved(c) for c in children.get(link, []))

    for name, driven in moving:
        if moved(driven) <= 0:
            raise LolgpsError(
                f"{path}: joint {name!r} moves no mass (link {driven!r} and every link it "
                f"carries have no <inertial> or mass 0); add the mass and inertia of {driven!r}"
            )
    massless = [driven for _, driven in moving if mass.get(driven, 0.0) <= 0]
    if massless and len(massless) == len(moving):
        raise LolgpsError(
            f"{path}: no link that the arm's joints move has mass ({', '.join(map(repr, massless))}"
            f" have no <inertial> or mass 0): a kinematic-only description; add the links' "
            f"<inertial> (mass and inertia)"
        )
    if massless:
        warnings.warn(
            f"{path}: link(s) {', '.join(map(repr, massless))} moved by an actuated joint have "
            f"no <inertial> (or mass 0): taken as massless, the URDF default; the joint still "
            f"moves the mass it carries.  Add their mass and inertia if they have any",
            ArmWarning,
            stacklevel=3,
        )
    return massless
