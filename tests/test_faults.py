"""Numerical failures during learning: reported per condition, never fatal to the stream."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import NumericalError
from lolgps_torch.lolgps import StreamConfig, make_learner
from lolgps_torch.lolgps import stream as stream_module
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.task import PegTask, TaskConfig

KUKA = "robots/kuka_peg.urdf"


@pytest.fixture(scope="module")
def task() -> Iterator[PegTask]:
    t = PegTask(TaskConfig(urdf=KUKA), n_worlds=2)
    yield t
    t.close()


def _tiny() -> StreamConfig:
    d = StreamConfig()
    return StreamConfig(
        max_iterations=3,
        success_phases=1,
        local=LocalConfig(samples=2),
        policy=replace(d.policy, steps=30),
    )


def test_a_numerical_failure_fails_its_condition_and_the_stream_goes_on(
    task: PegTask, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = stream_module.iterate

    def failing(*args: Any) -> Any:
        condition, iteration, _ = args[-1]
        if (condition, iteration) == (1, 1):
            raise NumericalError("Quu is not positive definite even at eta = 1e+10")
        return real(*args)

    monkeypatch.setattr(stream_module, "iterate", failing)
    folder = RunFolder(tmp_path / "run")
    learner = make_learner("lolgps", task, _tiny(), folder, lambda record: None)
    summary = learner.run([(0.0, 0.0), (0.01, 0.0), (0.0, 0.01)], lambda entry: None)
    assert [e.failure for e in summary] == [
        None,
        "iteration 1: Quu is not positive definite even at eta = 1e+10",
        None,
    ]
    failed = summary[1]
    assert failed.iterations == 2 and not failed.local_success
    # the stream went on: the next condition was learnt and every condition is in the replay
    assert summary[2].iterations >= 1
    assert ReplayBuffer(folder.replay_path).conditions() == [0, 1, 2]
    assert folder.read_entry(1)["failure"].startswith("iteration 1: Quu")


def test_a_blown_up_simulation_is_a_numerical_error(task: PegTask) -> None:
    world = task.sampler.worlds[0]
    world.reset(task.q0.cpu().numpy())
    with pytest.raises(NumericalError, match="non-finite action"):
        world.step(np.full(task.layout.dU, np.nan))
