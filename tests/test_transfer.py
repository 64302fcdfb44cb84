"""Forward transfer as Continual World defines it, on hand-made numbers."""

from __future__ import annotations

import pytest

from lolgps_torch.evaluation.transfer import forward_transfer, rates_by_condition, success_auc


def test_auc_pads_a_finished_condition_with_its_last_rate() -> None:
    assert success_auc([0.0, 0.2, 0.6, 1.0], horizon=10) == pytest.approx(
        (0.0 + 0.2 + 0.6 + 7 * 1.0) / 10
    )
    assert success_auc([0.5] * 12 + [0.0], horizon=10) == 0.5  # later iterations ignored


def test_forward_transfer_on_a_hand_made_example() -> None:
    scratch = success_auc([0, 0, 0.2, 0.4, 0.6, 0.8, 1, 1, 1, 1])  # 0.6
    transferred = success_auc([0.8, 1.0, 1.0])  # 0.98
    assert scratch == pytest.approx(0.6) and transferred == pytest.approx(0.98)
    assert forward_transfer(transferred, scratch) == pytest.approx(0.95)
    assert forward_transfer(0.25, 0.5) == pytest.approx(-0.5)  # negative transfer
    assert forward_transfer(1.0, 1.0) is None


def test_rates_come_from_iteration_records_only() -> None:
    records = [
        {"condition": 0, "iteration": 0, "success_rate": 0.0},
        {"condition": 0, "event": "distilled", "time_distill": 1.0},
        {"condition": 0, "iteration": 1, "success_rate": 0.4},
        {"condition": 1, "iteration": 0, "success_rate": 1.0},
    ]
    assert rates_by_condition(records) == {0: [0.0, 0.4], 1: [1.0]}
