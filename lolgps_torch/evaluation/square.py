"""The 2-D stream: hole positions uniform in a square centred on the nominal hole.

Training positions are ``count`` draws from the run's seed, arriving one at a time in stages
of ``stage_size``; the test set is ``test_positions`` draws from the evaluation's area seed,
from a separate random stream, so it never repeats a training position. Positions are planar
hole offsets ``(dx, dy)`` in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import Stage

Position = tuple[float, float]
TEST_STREAM = 7919  # the test positions' generator is seeded apart from the training one


@dataclass(frozen=True)
class SquareConfig:
    """:param side: the square's side (m). :param count: training positions.
    :param stage_size: conditions per stage (a checkpoint the evaluation tests).
    :param test_positions: held-out test positions."""

    side: float = 0.20
    count: int = 24
    stage_size: int = 8
    test_positions: int = 200

    def __post_init__(self) -> None:
        if not (0.0 < self.side < float("inf")):
            raise LolgpsError(f"square side {self.side}: must be a positive length (m)")
        if self.count < 1 or self.stage_size < 1 or self.test_positions < 1:
            raise LolgpsError("the square stream needs count, stage size and test positions >= 1")


def _uniform(n: int, side: float, generator: torch.Generator) -> list[Position]:
    drawn = (torch.rand(n, 2, dtype=torch.float64, generator=generator) - 0.5) * side
    return [(float(dx), float(dy)) for dx, dy in drawn.tolist()]


def square_stream(config: SquareConfig, seed: int) -> tuple[list[Position], list[Stage]]:
    """``count`` training positions from ``seed``, and stages ``square<i>`` of ``stage_size``
    conditions (the last one shorter when ``count`` is not a multiple)."""
    conditions = _uniform(config.count, config.side, torch.Generator().manual_seed(seed))
    lasts = list(range(config.stage_size - 1, config.count - 1, config.stage_size))
    lasts.append(config.count - 1)
    return conditions, [{"name": f"square{i}", "last_condition": k} for i, k in enumerate(lasts)]


def square_test_positions(
    config: SquareConfig, area_seed: int, training: list[Position]
) -> list[Position]:
    """``test_positions`` positions uniform in the square from ``area_seed``, none equal to a
    training position."""
    generator = torch.Generator().manual_seed(area_seed * TEST_STREAM + 1)
    seen, out = set(training), list[Position]()
    while len(out) < config.test_positions:
        out += [p for p in _uniform(config.test_positions, config.side, generator) if p not in seen]
    return out[: config.test_positions]
