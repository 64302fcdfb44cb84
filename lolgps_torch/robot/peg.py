"""The peg: attached to an arm whose URDF carries none, or read from one that does.

Every arm ends in a *point frame* whose origin is the peg tip and whose +z axis points out
along the peg.  A URDF that carries its own peg names that frame ``peg_tip`` (its parent link
is the peg's collision body).  Otherwise a peg of the configured length and radius is attached
to the end-effector link along ``PegConfig.axis``: the URDF text is extended with two fixed
links (``lolgps_peg`` and ``lolgps_peg_tip``).  The two end-effector points of the state are
the tip, ``(0, 0, 0)``, and the top, ``(0, 0, -point_separation)``, in the point frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from lolgps_torch.errors import LolgpsError

if TYPE_CHECKING:
    import yourdfpy

CARRIED_PEG_TIP = "peg_tip"
ATTACHED_PEG = "lolgps_peg"
ATTACHED_PEG_TIP = "lolgps_peg_tip"
# rpy that turns the point frame's +z onto each supported peg axis of the end-effector link.
_AXIS_RPY = {
    "x": (0.0, math.pi / 2, 0.0),
    "-x": (0.0, -math.pi / 2, 0.0),
    "y": (-math.pi / 2, 0.0, 0.0),
    "-y": (math.pi / 2, 0.0, 0.0),
    "z": (0.0, 0.0, 0.0),
    "-z": (math.pi, 0.0, 0.0),
}


PegAxis = Literal["auto", "x", "y", "z", "-x", "-y", "-z"]


@dataclass(frozen=True)
class PegConfig:
    """The peg attached to arms whose URDF has none (m), and the end-effector point spacing.

    :param length: peg length along ``axis`` from the end-effector link origin.
    :param radius: peg radius.
    :param axis: the end-effector link axis the peg points along: x, y, z, -x, -y or -z, or
        auto: the axis nearest the direction from the last actuated joint to the end-effector
        link (or, where they coincide, the last joint's roll axis, or the direction of the last
        link square to a pitching last joint's axis).
    :param point_separation: distance from the tip to the second (top) point on the axis.
    """

    length: float = 0.20
    radius: float = 0.015
    axis: PegAxis = "auto"
    point_separation: float = 0.15

    def __post_init__(self) -> None:
        for flag, value in (
            ("--peg-length", self.length),
            ("--peg-radius", self.radius),
            ("point separation", self.point_separation),
        ):
            if not (math.isfinite(value) and value > 0):
                raise LolgpsError(f"{flag} must be a positive length (m), got {value}")
        if self.axis != "auto" and self.axis not in _AXIS_RPY:
            raise LolgpsError(
                f"--peg-axis must be auto or one of {', '.join(_AXIS_RPY)}, got {self.axis!r}"
            )


def carried_peg_radius(robot: yourdfpy.URDF, link: str, path: str) -> float:
    """The radius of the cylinder of ``link``, the peg a URDF carries itself."""
    for collision in robot.link_map[link].collisions:
        if collision.geometry.cylinder is not None:
            return float(collision.geometry.cylinder.radius)
    raise LolgpsError(f"{path}: peg link {link!r} (parent of {CARRIED_PEG_TIP!r}) has no cylinder")


def auto_axis(chain: list[yourdfpy.Joint], actuated: list[yourdfpy.Joint]) -> str:
    """The end-effector link axis (+-x, y, z) nearest the direction, at q = 0, from the last
    actuated joint's origin to the link's origin; where the two coincide, the last joint's
    axis if it rolls along the arm (parallel, within 25 degrees, to the step from the joint
    before it), pointing away from that joint, or, if it pitches (its axis parallel to the
    joint before it), that step's part square to its axis; otherwise z."""
    pose, joints = np.eye(4), []
    for j in chain:
        pose = pose @ (j.origin if j.origin is not None else np.eye(4))
        if j in actuated:
            axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=float)
            joints.append((pose[:3, 3].copy(), pose[:3, :3] @ (axis / np.linalg.norm(axis))))
    out = pose[:3, 3] - joints[-1][0]
    if np.linalg.norm(out) < 1e-3:
        step = joints[-1][0] - joints[-2][0] if len(joints) > 1 else np.zeros(3)
        along = float(joints[-1][1] @ step)
        rolls = abs(along) >= 0.9 * np.linalg.norm(step) > 0
        # a last joint parallel to the one before it pitches the tool, which goes on from the
        # last link square to its axis (a 4-DoF arm's wrist: along that axis the peg would
        # never turn away from the horizontal)
        pitches = len(joints) > 1 and abs(float(joints[-1][1] @ joints[-2][1])) >= 0.9
        out = step - along * joints[-1][1] if pitches else np.zeros(3)
        if rolls:
            out = joints[-1][1] * np.sign(along)
        elif np.linalg.norm(out) < 1e-6:
            return "z"
    local = pose[:3, :3].T @ out
    i = int(np.argmax(np.abs(local)))
    return ("-" if local[i] < 0 else "") + "xyz"[i]


def attach_peg(text: str, ee_link: str, peg: PegConfig, axis: str) -> str:
    """Append a peg cylinder and its tip frame, fixed to ``ee_link`` along ``axis``."""
    r, p, y = _AXIS_RPY[axis]
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
