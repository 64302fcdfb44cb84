"""The spots where the placement (:mod:`lolgps_torch.robot.placement`) tries the nominal hole:
a grid about the preferred spot, in the arm's reach from its shoulder (:func:`candidates`),
and spots about the tips of sampled poses that point the peg down (:func:`cloud_candidates`),
the best of them spread apart (:func:`spread`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

# (rho, eta) offsets from the preferred fractions, and azimuths (degrees) about the base's +x,
# tried by the placement
STEPS = (0.0, -0.1, 0.1, -0.2, 0.2, 0.3)
# further height offsets (eta), tried once no spot of STEPS fits: arms that hang from their
# shoulder (an arm on a torso) or reach up to the table
FAR_HEIGHTS = (0.45, 0.6, 0.75, -0.3, -0.45)
AZIMUTHS = (0, 45, -45, 90, -90, 135, -135, 180)
START_SCALES = (1.0, 0.5)
# and with them: the start lower still, for arms whose wrist keeps the peg pointing down over a
# narrow band of heights only (example-robot-data's Talos arm: 0.05 m above the mouth, not 0.1)
FAR_START_SCALES = (1.0, 0.5, 0.25)
CLOUD_MOUTHS = 512  # sampled tips the last candidates are placed about


def candidates(
    shoulder: Tensor,
    radius: float,
    positions: Tensor,
    preferred: tuple[float, float, tuple[float, float, float]],
    steps: tuple[tuple[float, ...], tuple[float, ...]],
) -> tuple[Tensor, Tensor]:
    """Nominal mouths ``[C, 3]`` to try, preferred first, and the start tip's offset from each
    ``[C, 3]``.  A spot is ``shoulder + (rho R cos(a), rho R sin(a), -eta R)`` for azimuths a
    about the base's +x and fractions (rho, eta) about the preferred ones (``preferred``: rho,
    eta and the start tip's offset from the mouth; eta offset by the first of ``steps``); each
    is tried as
    it is, then shifted so that the positions' centre lies on it.  The start offset is turned
    by a (so that "back" points towards the base), and scaled by f, the second of ``steps``
    (1, then 0.5 for arms too short to lift the peg that high); the nearer (a, rho, eta, f) to (0, preferred, 1), the
    earlier."""
    reach_fraction, mouth_below_shoulder, start_offset = preferred
    centre = torch.nn.functional.pad(
        (positions.min(dim=0).values + positions.max(dim=0).values) / 2, (0, 1)
    )
    grid = sorted(
        (abs(a) / 45 + abs(r) / 0.1 + abs(e) / 0.1 + (1 - f) / 0.25, a, r, e, f)
        for a in AZIMUTHS
        for r in STEPS
        for e in steps[0]
        for f in steps[1]
        if 0.1 <= reach_fraction + r <= 0.95
    )
    mouths, starts = [], []
    dx, dy, dz = start_offset
    for _, a, r, e, f in grid:
        rho, eta = reach_fraction + r, mouth_below_shoulder + e
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        spot = shoulder + torch.tensor(
            [rho * radius * c, rho * radius * s, -eta * radius],
            dtype=torch.float64,
            device=shoulder.device,
        )
        start = torch.tensor(
            [f * (c * dx - s * dy), f * (s * dx + c * dy), f * dz],
            dtype=torch.float64,
            device=shoulder.device,
        )
        mouths += [spot, spot - centre]
        starts += [start, start]
    return torch.stack(mouths), torch.stack(starts)


def cloud_candidates(
    cloud_tip: Tensor, positions: Tensor, depth: float, start_offset: tuple[float, float, float]
) -> tuple[Tensor, Tensor]:
    """Nominal mouths ``[C, 3]`` placed about the sampled down-pointing tips ``[P, 3]`` (the
    stream's centre floor at a tip, at most :data:`CLOUD_MOUTHS` of them), each with ``start_offset``
    turned to every azimuth of :data:`AZIMUTHS` and scaled by every factor of
    :data:`FAR_START_SCALES` ``[C, 3]``: spots the grid of :func:`candidates` misses, for an
    arm that points the peg down only in a small or oddly placed part of its reach (one that
    hangs from a torso beside it)."""
    centre = (positions.min(dim=0).values + positions.max(dim=0).values) / 2
    stride = max(1, math.ceil(cloud_tip.shape[0] / CLOUD_MOUTHS))
    spots = cloud_tip[::stride] - torch.nn.functional.pad(centre, (0, 1), value=-depth)
    dx, dy, dz = start_offset
    offsets = [
        [
            f * (math.cos(a) * dx - math.sin(a) * dy),
            f * (math.sin(a) * dx + math.cos(a) * dy),
            f * dz,
        ]
        for a in map(math.radians, AZIMUTHS)
        for f in FAR_START_SCALES
    ]
    starts = torch.tensor(offsets, dtype=torch.float64, device=cloud_tip.device)
    mouths = spots[:, None].expand(-1, len(starts), -1).reshape(-1, 3)
    return mouths, starts.repeat(spots.shape[0], 1)


def spread(mouths: Tensor, starts: Tensor, order: list[int], apart: float, most: int) -> list[int]:
    """The candidates of ``order`` whose mouth or start tip lies more than ``apart`` (m) from
    those of every earlier one kept, at most ``most`` of them."""
    spots = torch.cat([mouths, mouths + starts], dim=-1)  # [C, 6]
    kept: list[int] = []
    for c in order:
        if kept:
            near = (spots[kept] - spots[c]).reshape(-1, 2, 3).norm(dim=-1).max(dim=-1).values
            if bool((near <= apart).any()):
                continue
        kept.append(c)
        if len(kept) == most:
            break
    return kept
