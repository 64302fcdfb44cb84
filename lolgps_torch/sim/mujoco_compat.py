"""What differs between the MuJoCo releases the package runs on (3.3.7 up to 4.x), tested by
feature, not by version number, so that a release in between, or a later one, takes whichever
form it has:

- the dense mass matrix (:func:`mass_matrix`): ``mj_fullM`` was handed the packed matrix
  ``mjData.qM`` (``mj_fullM(m, dst, qM)``) until 3.10 made it read the data itself
  (``mj_fullM(m, d, dst)``); 3.11 removed ``qM``;
- multi-point convex contact (``multiccd``): an enable flag ``mjENBL_MULTICCD``, off by
  default, until 3.8 turned it on and made it a disable flag ``mjDSBL_MULTICCD``; 4.0 gives the
  old enable bit (16) to sleeping (``mjENBL_SLEEP``), so the flag is only ever set by name;
- the margin and gap of a contact between two geoms: the larger of their values until 3.5,
  their sum since.

:func:`same_contact` sets the last two explicitly, so that every release is given the same
contact model. Measured with the KUKA (3.3.7 against 4.0.1): free motion is the same to
rounding (1e-13 over 40 control steps of random torques); pushed down by 30 N onto the table or
the hole for 60 steps, the peg's tip takes paths up to 7 mm apart and comes to rest within
1.2 mm, since 3.8 reimplemented multi-point contact (with it off in both, up to 1.4 mm apart).
"""

from __future__ import annotations

import re

import mujoco
import numpy as np

_FULLM_SECOND = re.match(r"mj_fullM\(m: [\w.]+, (\w+):", mujoco.mj_fullM.__doc__ or "")
# whether this release's mj_fullM reads the matrix from the data: its second parameter is the
# data ``d`` (3.10 on), not the output ``dst`` (before)
FULLM_READS_DATA = _FULLM_SECOND is not None and _FULLM_SECOND.group(1) == "d"


def mass_matrix(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """The joint-space mass matrix ``M(q) [nv, nv]`` of data ``d`` (after ``mj_fwdPosition``
    or ``mj_forward``), dense."""
    full = np.zeros((m.nv, m.nv))
    if FULLM_READS_DATA:
        mujoco.mj_fullM(m, d, full)
    else:
        mujoco.mj_fullM(m, full, d.qM)
    return full


def same_contact(spec: mujoco.MjSpec) -> None:
    """Set the contact settings whose default or meaning changed between releases to one
    value for all: multi-point convex contact on (the default since 3.8), and every geom's
    margin and gap zero (the summed and the larger of two zeros agree)."""
    enable = getattr(mujoco.mjtEnableBit, "mjENBL_MULTICCD", None)
    disable = getattr(mujoco.mjtDisableBit, "mjDSBL_MULTICCD", None)
    if enable is not None:
        spec.option.enableflags |= int(enable)
    if disable is not None:
        spec.option.disableflags &= ~int(disable)
    for geom in spec.geoms:
        geom.margin = 0.0
        geom.gap = 0.0
