"""The 2-D stream and its held-out test set."""

from __future__ import annotations

import pytest

from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.square import SquareConfig, square_stream, square_test_positions


def test_square_stream_is_seeded_uniform_and_staged() -> None:
    config = SquareConfig()
    conditions, stages = square_stream(config, seed=3)
    assert len(conditions) == 24 and conditions == square_stream(config, seed=3)[0]
    assert conditions != square_stream(config, seed=4)[0]
    assert all(abs(dx) <= 0.1 and abs(dy) <= 0.1 for dx, dy in conditions)
    assert [s["last_condition"] for s in stages] == [7, 15, 23]
    _, uneven = square_stream(SquareConfig(count=10, stage_size=4), seed=0)
    assert [s["last_condition"] for s in uneven] == [3, 7, 9]


def test_square_test_set_is_held_out_and_spread() -> None:
    config = SquareConfig()
    training, _ = square_stream(config, seed=0)
    test = square_test_positions(config, area_seed=0, training=training)
    assert len(test) == 200 and not set(test) & set(training)
    assert test == square_test_positions(config, area_seed=0, training=training)
    xs = sorted(p[0] for p in test)
    # uniform in [-0.1, 0.1]: each half of the square holds about half the positions
    assert 70 < sum(x < 0 for x in xs) < 130 and xs[0] >= -0.1 and xs[-1] <= 0.1


def test_square_rejects_a_bad_geometry() -> None:
    with pytest.raises(LolgpsError):
        SquareConfig(side=float("nan"))
    with pytest.raises(LolgpsError):
        SquareConfig(count=0)
