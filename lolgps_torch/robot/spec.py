"""The arm as the method sees it, a plain record that the loader (:mod:`.arm`) fills from a
URDF and everything else reads: the kinematics, the rigid-body model (:mod:`.rigid_body`),
the derived torque limits (:mod:`.effort`), the placement and the simulator.  It imports
nothing of the package, so that the loader can build on the modules that read it."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

# a URDF <inertia>'s attributes, as entries of the tensor
INERTIA_ENTRIES = {
    "ixx": (0, 0),
    "ixy": (0, 1),
    "ixz": (0, 2),
    "iyy": (1, 1),
    "iyz": (1, 2),
    "izz": (2, 2),
}
INERTIA_KEYS = tuple(INERTIA_ENTRIES)


def add_inertial(link: ET.Element, com: np.ndarray, mass: float, inertia: np.ndarray) -> None:
    """Append to the URDF ``link`` an ``<inertial>``: ``mass`` (kg) at ``com`` (m, in the
    link's frame) with the ``inertia`` tensor about it (``3 x 3``, the link's axes)."""
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", xyz=" ".join(repr(float(c)) for c in com), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=repr(float(mass)))
    entries = {k: repr(float(inertia[i, j])) for k, (i, j) in INERTIA_ENTRIES.items()}
    ET.SubElement(inertial, "inertia", entries)


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
    :param effort: torque limits (N m; derived from the arm where the URDF gives 0 or none,
        :mod:`.effort`). :param velocity: velocity limits (rad/s).
    :param point_offsets: the tip and top points in the point frame, ``((x, y, z), (x, y, z))``.
    :param peg_radius: peg radius (m), from the URDF or the attached peg.
    :param peg_axis: the end-effector link's axis the attached peg points along ("" for a peg
        the URDF carries).
    :param base_link: the link the arm's chain starts from (the root unless chosen).
    :param held: every joint of the description that could move but is held fixed (above the
        base link, off the chain, mimic or prismatic), with the position it is held at (rad or
        m), in the description's order.
    :param unbounded: the actuated joints without position limits (continuous joints; their
        ``lower`` and ``upper`` are only a range for placement).
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
    peg_axis: str = ""
    base_link: str = ""
    held: tuple[tuple[str, float], ...] = ()
    unbounded: tuple[str, ...] = ()

    @property
    def bounded(self) -> tuple[bool, ...]:
        """Per actuated joint, whether it has position limits."""
        return tuple(name not in self.unbounded for name in self.joint_names)

    @property
    def dof(self) -> int:
        return len(self.joint_names)
