"""Forward transfer: the metric as Continual World defines it, on hand-made numbers, and the
stream's transfer at a condition the policy already does."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.evaluation.transfer import forward_transfer, rates_by_condition, success_auc
from lolgps_torch.lolgps import StreamConfig, stream
from lolgps_torch.lolgps.stream import StreamLearner
from lolgps_torch.task import PegTask, TaskConfig

ROOT = Path(__file__).resolve().parents[1]


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
def kuka_task() -> Iterator[PegTask]:
    task = PegTask(TaskConfig(urdf=str(ROOT / "robots" / "kuka_peg.urdf")), n_worlds=5)
    yield task
    task.close()


@pytest.mark.slow  # three conditions with the default S-step; the phases alone: the next test
def test_a_condition_the_policy_already_does_costs_fewer_rollouts(
    kuka_task: PegTask, tmp_path: Path
) -> None:
    """The policy learnt at one hole, then the same hole again as a new condition (where the
    policy is known to succeed: its rollout right after the S-step is the probe's): with
    transfer it is learnt for ``transfer_phases`` iterations with successes after the probe,
    without it for ``success_phases``, from the same folder after the first condition; either
    way D_g is labelled by a local controller whose noiseless rollout succeeds."""
    config = StreamConfig(
        transfer="policy", success_phases=2, transfer_phases=1, max_iterations=12
    )  # the default S-step: a shorter one's policy may pass a limit at the hole, a miss
    first = StreamLearner(kuka_task, config, RunFolder(tmp_path / "transfer"), lambda r: None)
    entry = first.learn_condition(0, (0.0, 0.0))
    assert entry.policy_success_after  # the policy does the first hole
    shutil.copytree(tmp_path / "transfer", tmp_path / "none")
    second = StreamLearner(
        kuka_task, replace(config, transfer="none"), RunFolder(tmp_path / "none"), lambda r: None
    )
    assert len(second._restore()) == 1
    again = (0.0, 0.0)
    transferred, learnt = first.learn_condition(1, again), second.learn_condition(1, again)
    assert transferred.rollouts == 1 + config.local.samples < learnt.rollouts
    assert transferred.iterations == 1 and transferred.successful_samples > 0
    assert transferred.policy_success_after and learnt.policy_success_after
    assert transferred.local_success and learnt.local_success
    stored = ReplayBuffer(RunFolder(tmp_path / "transfer").replay_path).read_condition(1)
    assert stored.p_cur is not None and stored.p_pre is not None  # a teacher, not the policy


def test_a_probe_that_succeeds_cuts_the_phases_to_transfer_phases_never_above_success_phases(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    learner = object.__new__(StreamLearner)
    learner.task = SimpleNamespace(config=SimpleNamespace(world=SimpleNamespace(success_threshold=0.06)))  # fmt: skip
    learner.policy = SimpleNamespace(trained=True)
    probe = [0.01]
    monkeypatch.setattr(stream, "policy_distances", lambda task, policy, offsets: probe)
    learner.config = StreamConfig(success_phases=9, transfer_phases=3)
    assert learner.phases((0.0, 0.0)) == (3, 1)  # the probe succeeded
    probe[0] = 0.2
    assert learner.phases((0.0, 0.0)) == (9, 1)  # it missed: the paper's phases, probe counted
    probe[0] = 0.01
    learner.config = StreamConfig(success_phases=1, transfer_phases=3)
    assert learner.phases((0.0, 0.0)) == (1, 1)
    learner.config = StreamConfig(transfer="none")
    assert learner.phases((0.0, 0.0)) == (9, 0)  # no probe
    learner.config, learner.policy.trained = StreamConfig(), False
    assert learner.phases((0.0, 0.0)) == (9, 0)  # nothing to transfer yet
