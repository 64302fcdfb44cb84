"""Faults during learning: a numerical failure is reported per condition and the stream goes on;
a full disk stops the run with one error naming the file, keeps what was written before and
lets the run resume."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
import torch

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.checkpoint import load_policy, save_policy
from lolgps_torch.data.records import DistillRecord, IterationRecord
from lolgps_torch.data.run_folder import RunFolder, write_json
from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.lolgps import StreamConfig, make_learner
from lolgps_torch.lolgps import stream as stream_module
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.policy import GaussianPolicy, PolicyConfig
from lolgps_torch.task import PegTask, TaskConfig

KUKA = "robots/kuka_peg.urdf"


@pytest.fixture(scope="module")
def task() -> Iterator[PegTask]:
    t = PegTask(TaskConfig(urdf=KUKA), n_worlds=2)
    yield t
    t.close()


def _tiny() -> StreamConfig:
    """A small stream: each condition from the hold (no plan on the model), one S-step a
    condition (no repair or on-policy rounds), the policy's rollouts without the guard: none of
    which these faults concern."""
    d = StreamConfig()
    return StreamConfig(
        max_iterations=3,
        success_phases=1,
        repairs=0,
        onpolicy_rounds=0,
        local=LocalConfig(samples=2, model_plans=0),
        policy=replace(d.policy, steps=30, guard=False),
    )


def test_a_numerical_failure_fails_its_condition_and_the_stream_goes_on(
    task: PegTask, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = stream_module.iterate

    def failing(*args: Any) -> Any:
        condition, iteration, _ = args[4]  # where: (condition, iteration, alpha)
        if (condition, iteration) == (1, 0):
            raise NumericalError("Quu is not positive definite even at eta = 1e+10")
        return real(*args)

    monkeypatch.setattr(stream_module, "iterate", failing)
    folder = RunFolder(tmp_path / "run")
    learner = make_learner("lolgps", task, _tiny(), folder, lambda record: None)
    summary = learner.run([(0.0, 0.0), (0.01, 0.0), (0.0, 0.01)], lambda entry: None)
    assert [e.failure for e in summary] == [
        None,
        "iteration 0: Quu is not positive definite even at eta = 1e+10",
        None,
    ]
    failed = summary[1]
    assert failed.iterations == 1 and not failed.local_success
    # the stream went on: the next condition was learnt and every condition is in the replay
    assert summary[2].iterations >= 1
    assert ReplayBuffer(folder.replay_path).conditions() == [0, 1, 2]
    assert folder.read_entry(1)["failure"].startswith("iteration 0: Quu")


def test_a_blown_up_simulation_is_a_numerical_error(task: PegTask) -> None:
    world = task.sampler.worlds[0]
    world.reset(task.q0.cpu().numpy())
    with pytest.raises(NumericalError, match="non-finite action"):
        world.step(np.full(task.layout.dU, np.nan))


# -- a full disk ---------------------------------------------------------------------------
# Linux's /dev/full fails every write with ENOSPC: a file linked to it stands for a full disk.
DEV_FULL = Path("/dev/full")
needs_dev_full = pytest.mark.skipif(not DEV_FULL.exists(), reason="needs /dev/full")
FULL = "No space left on device"


def _group_bytes(path: Path, group: str) -> dict[str, bytes]:
    with h5py.File(path, "r") as f:
        return {name: np.asarray(ds).tobytes() for name, ds in f[group].items()}


@needs_dev_full
def test_a_full_disk_stops_the_run_with_one_error_and_the_run_resumes(
    task: PegTask, tmp_path: Path
) -> None:
    folder = RunFolder(tmp_path / "run")
    conditions = [(0.0, 0.0), (0.01, 0.0)]
    temporary = folder.path / "replay.h5.partial"

    def fill_the_disk_after_the_last_s_step(record: IterationRecord | DistillRecord) -> None:
        if isinstance(record, DistillRecord) and record.condition == 1:
            temporary.symlink_to(DEV_FULL)  # where the replay's next append is written

    learner = make_learner("lolgps", task, _tiny(), folder, fill_the_disk_after_the_last_s_step)
    with pytest.raises(LolgpsError) as raised:
        learner.run(conditions, lambda entry: None)
    assert str(raised.value) == f"disk full while writing {folder.replay_path}: {FULL}"
    assert not temporary.is_symlink()  # the temporary file is removed
    # what was written before stays readable: the first condition's replay group and policy
    replay = ReplayBuffer(folder.replay_path)
    assert replay.conditions() == [0]
    before = _group_bytes(folder.replay_path, "condition_000")
    load_policy(folder.checkpoint_dir(0))
    entry = folder.read_entry(0)

    # space is back: the run resumes at the second condition and leaves the first untouched
    resumed = make_learner("lolgps", task, _tiny(), folder, lambda record: None)
    summary = resumed.run(conditions, lambda entry: None)
    assert [e.condition for e in summary] == [0, 1]
    assert replay.conditions() == [0, 1]
    assert _group_bytes(folder.replay_path, "condition_000") == before
    assert folder.read_entry(0) == entry
    load_policy(folder.checkpoint_dir(1))


@needs_dev_full
def test_a_full_disk_while_logging_or_writing_json_names_the_file(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path / "run")
    folder.append_metrics({"iteration": 0})
    write_json(folder.summary_path, {"conditions": []})
    metrics = folder.metrics_path.read_text()
    folder.metrics_path.unlink()
    folder.metrics_path.symlink_to(DEV_FULL)
    with pytest.raises(
        LolgpsError, match=f"^disk full while writing {folder.metrics_path}: {FULL}$"
    ):
        folder.append_metrics({"iteration": 1})
    partial = folder.path / "summary.json.partial"
    partial.symlink_to(DEV_FULL)
    with pytest.raises(
        LolgpsError, match=f"^disk full while writing {folder.summary_path}: {FULL}$"
    ):
        folder.write_summary({"conditions": [1]})
    assert folder.read_summary() == {"conditions": []}  # the previous file is kept
    assert not partial.is_symlink() and metrics == '{"iteration": 0}\n'


@needs_dev_full
def test_a_full_disk_while_saving_a_policy_is_one_error(tmp_path: Path) -> None:
    old, new = GaussianPolicy(3, 2), GaussianPolicy(3, 2, PolicyConfig(seed=1))
    x = torch.randn(4, 3, dtype=torch.float64)
    save_policy(tmp_path, old)
    for name in ("policy.pt", "policy.json"):
        partial = tmp_path / f"{name}.partial"
        partial.symlink_to(DEV_FULL)
        with pytest.raises(
            LolgpsError, match=f"^disk full while writing {tmp_path / name}: {FULL}$"
        ):
            save_policy(tmp_path, new)
        assert not partial.is_symlink()
        if name == "policy.pt":  # nothing was replaced: the previous checkpoint loads
            assert torch.equal(load_policy(tmp_path)(x), old(x))
    # new weights beside the old description (their SHA-256) are reported, never mixed
    with pytest.raises(LolgpsError, match="policy.pt: its SHA-256 differs"):
        load_policy(tmp_path)
    save_policy(tmp_path, new)
    assert torch.equal(load_policy(tmp_path)(x), new(x))
