"""What both engines build alike, described once: the table and the tilted-plate funnel as
boxes (:func:`hole_boxes`), and where rotor-like inertia is added because joint damping would
be unstable (:func:`damping_inertias`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from lolgps_torch.sim.simulator import WorldConfig


class Box(NamedTuple):
    """One box of the hole, in the hole's frame (the mouth's centre): half extents (m), and a
    pose ``Rz(yaw) (Ry(tilt) x + centre)``: turned by ``tilt`` about y, moved to ``centre``,
    then the whole turned by ``yaw`` about the hole's vertical axis.  ``yaw`` None: the box
    is not turned at all (the floor, which PyBullet places without composing transforms,
    as those round to single precision)."""

    half_extents: list[float]
    centre: list[float]
    yaw: float | None
    tilt: float


def hole_boxes(peg_radius: float, config: WorldConfig) -> list[Box]:
    """The table slab with a square opening and the funnel under it, as boxes: four guide
    plates tilted so the clearance per side narrows from ``clearance_mouth`` at the table
    surface to ``clearance_bottom`` at the floor, ``depth`` below; a pinwheel of four slabs
    around the opening; the floor."""
    a_top = peg_radius + config.clearance_mouth
    a_bot = peg_radius + config.clearance_bottom
    h, D, W = config.plate_thickness / 2, config.depth, config.table_half_size
    norm = math.hypot(D, a_bot - a_top)
    nx, nz = D / norm, (a_bot - a_top) / norm  # outward normal of the +x plate's face
    face_mid = np.array([(a_top + a_bot) / 2, 0.0, -D / 2])
    centre = (face_mid + h * np.array([nx, 0.0, nz])).tolist()
    tilt = math.atan2(-nz, nx)
    quarter = [k * math.pi / 2 for k in range(4)]
    plates = [Box([h, a_top + 2 * h, norm / 2], centre, yaw, tilt) for yaw in quarter]
    outer = a_top + 2 * h  # the slab leaves a square opening of this half-width
    zc, zh = -(D + 2 * h) / 2, (D + 2 * h) / 2
    slab = [(W - outer) / 2, (W + outer) / 2, zh]
    slabs = [Box(slab, [(outer + W) / 2, (W - outer) / 2, zc], yaw, 0.0) for yaw in quarter]
    return [*plates, *slabs, Box([outer, outer, h], [0.0, 0.0, -D - h], None, 0.0)]


def damping_inertias(
    mass_matrix: np.ndarray, index: Sequence[int], damping: Sequence[float], config: WorldConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Per joint ``index[j]`` of ``mass_matrix`` (at q = 0; joint damping ``damping[j]``): its
    effective inertia ``m = 1 / (M^-1)_jj`` and the least inertia ``margin b h`` at which
    PyBullet's explicit joint damping is stable (h the physics step).  A world adds the
    difference, where m is below it, to the joint's child link as rotor-like inertia."""
    dt = config.dt / config.substeps
    m_eff = 1.0 / np.diag(np.linalg.inv(mass_matrix))[list(index)]
    need = np.array([config.damping_margin * b * dt for b in damping])
    return m_eff, need
