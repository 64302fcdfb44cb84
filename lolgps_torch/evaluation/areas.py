"""Test areas and the default training stream of the experiment (docs/ALGORITHM.md section 9, Fig. 3).

Test area ``k = 0 .. K-1`` is a disc of radius ``r`` centred ``c_k = k * spacing * e_axis`` from
the nominal hole position, ``e_axis`` the unit vector of the table's lateral axis. Positions are
planar hole offsets ``(dx, dy)`` in metres, as the task's conditions; tensors are float64 and
area-first: ``[K, P, 2]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError

Stage = dict[str, Any]  # {"name": "train0", "last_condition": 3}


@dataclass(frozen=True)
class AreaConfig:
    """Geometry of the test areas (paper Fig. 3; the paper gives no numbers, these are
    docs/ALGORITHM.md section 9's defaults).

    :param n_areas: number of test areas K.
    :param spacing: distance (m) between consecutive area centres; area 0 is centred on the
        nominal hole.
    :param radius: radius (m) of each area's disc.
    :param positions_per_area: test positions P drawn uniformly in each disc (paper: 50).
    :param axis: the axis the centres lie along: ``"y"``, the table's lateral axis, or ``"x"``.
    :param seed: seed of the test positions.
    """

    n_areas: int = 7
    spacing: float = 0.05
    radius: float = 0.025
    positions_per_area: int = 50
    axis: Literal["x", "y"] = "y"
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_areas < 1 or self.positions_per_area < 1:
            raise LolgpsError(
                f"need at least one area and one position per area, got {self.n_areas} areas "
                f"of {self.positions_per_area} positions"
            )
        if self.radius <= 0 or self.spacing <= 0:
            raise LolgpsError(
                f"area radius and spacing must be positive, got radius "
                f"{self.radius} m, spacing {self.spacing} m"
            )
        if self.axis not in ("x", "y"):
            raise LolgpsError(f"area axis must be 'x' or 'y', got {self.axis!r}")


def area_centres(config: AreaConfig) -> Tensor:
    """Centres ``c_k = k * spacing * e_axis``, ``[K, 2]`` (m)."""
    centres = torch.zeros(config.n_areas, 2, dtype=torch.float64)
    centres[:, 0 if config.axis == "x" else 1] = config.spacing * torch.arange(
        config.n_areas, dtype=torch.float64
    )
    return centres


def _uniform_in_disc(n: int, radius: float, generator: torch.Generator) -> Tensor:
    """``n`` points uniform in a disc about the origin, ``[n, 2]``: ``rho = r sqrt(u1)``,
    ``phi = 2 pi u2`` (the square root makes the density uniform in area)."""
    u = torch.rand(n, 2, dtype=torch.float64, generator=generator)
    rho = radius * u[:, 0].sqrt()
    phi = 2.0 * math.pi * u[:, 1]
    return torch.stack([rho * phi.cos(), rho * phi.sin()], dim=-1)


def sample_area_positions(config: AreaConfig) -> Tensor:
    """Test positions ``[K, P, 2]``, uniform in each area's disc, from ``config.seed`` alone.

    Area ``k`` takes the ``k``-th block of ``P`` draws, so its positions do not change when
    areas are added after it.
    """
    generator = torch.Generator().manual_seed(config.seed)
    K, P = config.n_areas, config.positions_per_area
    offsets = _uniform_in_disc(K * P, config.radius, generator).reshape(K, P, 2)
    return area_centres(config)[:, None, :] + offsets


def area_of(positions: Tensor, config: AreaConfig) -> Tensor:
    """Index ``[N]`` (int64) of the area each position ``[N, 2]`` belongs to, -1 for none.

    A position belongs to the nearest centre on the row ``c_k = k * spacing * e_axis``,
    ``k = 0, 1, 2, ...``, if that centre is at most ``spacing`` away and ``k < n_areas``.
    Nearest centre rather than inside the disc: train0's square ``(+-0.02, +-0.02)`` lies
    0.028 m from the nominal, just outside area 0's default 0.025 m disc, yet trains it. The
    row is unbounded so that a position's area does not change with the number of areas.
    """
    positions = positions.to(torch.float64).reshape(-1, 2)
    along = positions[:, 0 if config.axis == "x" else 1]
    k = torch.round(along / config.spacing).clamp_min(0)
    centres = torch.zeros_like(positions)
    centres[:, 0 if config.axis == "x" else 1] = k * config.spacing
    inside = ((positions - centres).norm(dim=-1) <= config.spacing) & (k < config.n_areas)
    return torch.where(inside, k.long(), torch.full_like(k, -1, dtype=torch.long))


def default_training_stream(
    config: AreaConfig,
    seed: int,
    *,
    initial_half_width: float = 0.02,
    extra_areas: tuple[int, ...] = (2, 4),
    per_extra_area: int = 2,
) -> tuple[list[tuple[float, float]], list[Stage]]:
    """The paper's stream (docs/ALGORITHM.md section 9): ``train0`` = the 4 corners
    ``(+-w, +-w)`` of a square about the nominal hole; ``train<i>`` (i >= 1) adds
    ``per_extra_area`` positions drawn uniformly (seeded by ``seed``) in test area
    ``extra_areas[i-1]``'s disc.

    :returns: the conditions as ``(dx, dy)`` tuples in stream order, and the stages as
        ``{"name", "last_condition"}`` dicts (index of each stage's last condition).
    """
    if any(not 0 <= k < config.n_areas for k in extra_areas):
        raise LolgpsError(f"training areas {extra_areas} outside the {config.n_areas} test areas")
    w = initial_half_width
    conditions = [(-w, -w), (-w, w), (w, -w), (w, w)]
    stages: list[Stage] = [{"name": "train0", "last_condition": len(conditions) - 1}]
    generator = torch.Generator().manual_seed(seed)
    centres = area_centres(config)
    for i, k in enumerate(extra_areas, start=1):
        drawn = centres[k] + _uniform_in_disc(per_extra_area, config.radius, generator)
        conditions += [(float(dx), float(dy)) for dx, dy in drawn.tolist()]
        stages.append({"name": f"train{i}", "last_condition": len(conditions) - 1})
    return conditions, stages
