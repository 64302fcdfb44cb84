"""An arm described only in MJCF (``--mjcf FILE``, with ``--sim mujoco``), as the URDF text the
rest of the package reads (:func:`mjcf_urdf`).

MuJoCo compiles the file, so what its compiler computes (inertias from geoms, defaults,
``<include>`` files, the ``ref`` of a joint) arrives already resolved; the URDF is written from
the compiled model:

- every body becomes a link, named as the body (``body<i>`` if unnamed), and every named site
  a massless link fixed to its body's link, so that ``--ee-link`` may name a body or a site;
  the world body is the root link ``world``, to which the top-level bodies are fixed;
- a body's link frame is the body's frame moved to its joint's anchor (a URDF joint turns
  about its child link's origin); its inertial is the body's mass at its centre of mass with
  the inertia tensor turned into the link's axes;
- a hinge joint becomes a revolute joint (continuous without a range), a slide joint a
  prismatic one, their ranges measured from the joint's ``ref``; a joint's damping and
  frictionloss become its ``<dynamics>``, its torque limit the tightest of its
  ``actfrcrange`` and what a motor actuator on it can give (``gear * gain * ctrlrange`` or
  ``gear * forcerange``); without either the limit is 0, which the loader derives
  (:mod:`.effort`).

Left out: geoms (only the attached peg touches the world; the arm's shapes are not drawn),
joint armature, actuator dynamics (the learner drives the joints with torques), tendons and
equality constraints.  Refused with one line: a file MuJoCo cannot compile, a free or ball
joint (the arm's base must be fixed, its joints one-dimensional), a body with more than one
joint, and a site named as a body.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET

import mujoco
import numpy as np

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import add_inertial

ROOT_LINK = "world"
# MuJoCo's enum values an arm's model is read with, as plain integers: from 4.0 an enum no
# longer equals the numpy integer a model's array holds
HINGE, SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
FREE = int(mujoco.mjtJoint.mjJNT_FREE)
JOINT_TRANSMISSION, NO_BIAS = int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtBias.mjBIAS_NONE)
KINDS = {HINGE: "revolute", SLIDE: "prismatic"}  # URDF's joint of each type an arm may have


def _rpy(quat: np.ndarray) -> str:
    """The unit quaternion ``(w, x, y, z)`` as URDF's roll, pitch and yaw (``R = Rz Ry Rx``)."""
    R = _matrix(quat)
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return f"{roll!r} {pitch!r} {yaw!r}"


def _matrix(quat: np.ndarray) -> np.ndarray:
    """The rotation matrix of the unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = (float(v) for v in quat / np.linalg.norm(quat))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _xyz(v: np.ndarray) -> str:
    return " ".join(repr(float(c)) for c in v)


def _compile(path: str) -> mujoco.MjModel:
    """MuJoCo's compiled model of the file; one-line errors for a missing or bad file."""
    if not os.path.isfile(path):
        raise LolgpsError(f"MJCF not found: {path}")
    try:
        return mujoco.MjModel.from_xml_path(path)
    except ValueError as error:
        text = str(error).strip()
        first = text.splitlines()[0] if text else repr(error)
        raise LolgpsError(f"{path}: MuJoCo cannot compile it ({first})") from None


def _torque_limit(m: mujoco.MjModel, joint: int) -> float:
    """The joint's torque limit (module docstring), 0 when the file gives none."""
    limits = []
    if m.jnt_actfrclimited[joint]:
        limits.append(float(np.abs(m.jnt_actfrcrange[joint]).max()))
    for a in range(m.nu):
        if m.actuator_trntype[a] != JOINT_TRANSMISSION or m.actuator_trnid[a, 0] != joint:
            continue
        gear = abs(float(m.actuator_gear[a, 0]))
        if m.actuator_forcelimited[a]:
            limits.append(gear * float(np.abs(m.actuator_forcerange[a]).max()))
        elif m.actuator_ctrllimited[a] and m.actuator_biastype[a] == NO_BIAS:
            gain = abs(float(m.actuator_gainprm[a, 0]))
            limits.append(gear * gain * float(np.abs(m.actuator_ctrlrange[a]).max()))
    return min(limits) if limits else 0.0


def _name(m: mujoco.MjModel, kind: mujoco.mjtObj, index: int, fallback: str) -> str:
    """The object's name in the file, or ``fallback`` for an unnamed one."""
    return mujoco.mj_id2name(m, kind, index) or fallback


def mjcf_urdf(path: str) -> str:
    """The MJCF arm at ``path`` as URDF text (module docstring); a file that cannot be
    converted is a :class:`LolgpsError` naming what to change."""
    m = _compile(path)
    robot = ET.Element("robot", name=os.path.splitext(os.path.basename(path))[0])
    ET.SubElement(robot, "link", name=ROOT_LINK)
    links = [ROOT_LINK] + [
        _name(m, mujoco.mjtObj.mjOBJ_BODY, b, f"body{b}") for b in range(1, m.nbody)
    ]
    anchor = np.zeros((m.nbody, 3))  # each link's origin in its body's frame
    for b in range(1, m.nbody):
        name, parent = links[b], int(m.body_parentid[b])
        if m.body_mocapid[b] >= 0:
            raise LolgpsError(f"{path}: body {name!r} is a mocap body; an arm has none")
        if m.body_jntnum[b] > 1:
            raise LolgpsError(
                f"{path}: body {name!r} has {m.body_jntnum[b]} joints; URDF allows one a "
                f"link: split the body into one body per joint"
            )
        joint = int(m.body_jntadr[b]) if m.body_jntnum[b] else -1
        kind = "fixed"
        if joint >= 0:
            kind = KINDS.get(int(m.jnt_type[joint]), "")
            if not kind:
                moving = "free" if m.jnt_type[joint] == FREE else "ball"
                raise LolgpsError(
                    f"{path}: body {name!r} has a {moving} joint; an arm's base is fixed and "
                    f"its joints are hinges or slides"
                )
            anchor[b] = m.jnt_pos[joint]
        R = _matrix(m.body_quat[b])
        origin = m.body_pos[b] + R @ anchor[b] - anchor[parent]
        link = ET.SubElement(robot, "link", name=name)
        Ri = _matrix(m.body_iquat[b])
        inertia = Ri @ np.diag(m.body_inertia[b]) @ Ri.T
        add_inertial(link, m.body_ipos[b] - anchor[b], float(m.body_mass[b]), inertia)
        joint_name = (
            _name(m, mujoco.mjtObj.mjOBJ_JOINT, joint, f"joint{joint}")
            if joint >= 0
            else f"{name}_fixed"
        )
        _joint(robot, joint_name, kind, links[parent], name, origin, m.body_quat[b])
        if joint >= 0:
            _moving(robot[-1], m, joint)
    for site in range(m.nsite):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, site)
        if not name:
            continue
        if name in links:
            raise LolgpsError(f"{path}: site {name!r} has a body's name; rename one of them")
        body = int(m.site_bodyid[site])
        ET.SubElement(robot, "link", name=name)
        origin = m.site_pos[site] - anchor[body]
        _joint(robot, f"{name}_fixed", "fixed", links[body], name, origin, m.site_quat[site])
        links.append(name)
    return ET.tostring(robot, encoding="unicode")


def _joint(
    robot: ET.Element,
    name: str,
    kind: str,
    parent: str,
    child: str,
    xyz: np.ndarray,
    quat: np.ndarray,
) -> None:
    """A URDF joint of type ``kind`` placing ``child``'s frame at ``xyz``, turned by ``quat``,
    in ``parent``'s."""
    element = ET.SubElement(robot, "joint", name=name, type=kind)
    ET.SubElement(element, "parent", link=parent)
    ET.SubElement(element, "child", link=child)
    ET.SubElement(element, "origin", xyz=_xyz(xyz), rpy=_rpy(quat))


def _moving(element: ET.Element, m: mujoco.MjModel, joint: int) -> None:
    """The axis, limits and dynamics of the moving joint ``element``, MuJoCo's ``joint``."""
    ET.SubElement(element, "axis", xyz=_xyz(m.jnt_axis[joint]))
    dof = int(m.jnt_dofadr[joint])
    # MJCF gives no joint speeds: 0, so that the loader derives one, as for a URDF joint
    limit = {"effort": repr(_torque_limit(m, joint)), "velocity": "0"}
    if m.jnt_limited[joint]:
        low, high = np.asarray(m.jnt_range[joint]) - m.qpos0[m.jnt_qposadr[joint]]
        limit |= {"lower": repr(float(low)), "upper": repr(float(high))}
    elif element.get("type") == "revolute":
        element.set("type", "continuous")
    ET.SubElement(element, "limit", limit)
    damping, friction = float(m.dof_damping[dof]), float(m.dof_frictionloss[dof])
    ET.SubElement(element, "dynamics", damping=repr(damping), friction=repr(friction))
