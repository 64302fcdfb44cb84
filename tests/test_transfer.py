"""Forward transfer: the metric on hand-made numbers, and a stream that reuses its policy."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.evaluation.transfer import forward_transfer, rates_by_condition, success_auc
from lolgps_torch.lolgps import StreamConfig, make_learner
from lolgps_torch.task import PegTask, TaskConfig


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


@pytest.fixture(scope="module")
def task() -> Iterator[PegTask]:
    t = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=5)
    yield t
    t.close()


def test_a_condition_the_policy_already_solves_costs_fewer_rollouts(
    task: PegTask, tmp_path: Path
) -> None:
    config = StreamConfig(max_iterations=12, success_phases=4, transfer_phases=1)
    learned = RunFolder(tmp_path / "policy")
    first = make_learner("lolgps", task, config, learned, lambda r: None).run([(0.0, 0.0)], print)
    assert first[0].policy_success_after  # learning happened at the first condition
    shutil.copytree(learned.path, tmp_path / "none")
    stream = [(0.0, 0.0), (0.005, 0.0)]  # the second hole is 5 mm from the first
    with_transfer = make_learner("lolgps", task, config, learned, lambda r: None)
    without = make_learner(
        "lolgps", task, replace(config, transfer="none"), RunFolder(tmp_path / "none"), print
    )
    known = with_transfer.run(stream, lambda e: None)[1]
    scratch = without.run(stream, lambda e: None)[1]
    assert known.start == "known" and scratch.start == "hold"
    assert known.rollouts < scratch.rollouts
    assert known.policy_success_after
