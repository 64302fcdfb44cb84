"""Batch GPS is MDGPS: after the first S-step each C-step is anchored to the policy's
linearisation at that condition's new samples, and each S-step sees every condition."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.records import DistillRecord, IterationRecord
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps import StreamConfig, make_learner, method_config
from lolgps_torch.lolgps import batch as batch_module
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian


def test_mdgps_c_step_is_anchored_to_the_policy_linearisation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    linearised: list[LinearGaussian] = []
    anchors: list[LinearGaussian] = []
    real_linearize, real_improve = batch_module.linearize_policy, LocalLearner.improve

    def linearize(*args: Any) -> LinearGaussian:
        linearised.append(real_linearize(*args))
        return linearised[-1]

    def improve(self: LocalLearner, fit: Any, p_bar: LinearGaussian) -> Any:
        anchors.append(p_bar)
        return real_improve(self, fit, p_bar)

    monkeypatch.setattr(batch_module, "linearize_policy", linearize)
    monkeypatch.setattr(LocalLearner, "improve", improve)
    d = StreamConfig()
    config = replace(
        d,
        max_iterations=2,
        success_phases=5,
        local=LocalConfig(samples=2, model_plans=0),  # from the hold: no plan needed
        policy=replace(d.policy, steps=20),
    )
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=2)
    records: list[IterationRecord | DistillRecord] = []
    folder = RunFolder(tmp_path / "batch")
    summary = make_learner("batch", task, config, folder, records.append).run(
        [(0.0, 0.0), (0.01, 0.0)], lambda e: None
    )
    task.close()
    # iteration 0: no policy yet, trust region; iteration 1: both anchored to the fresh p_pre
    assert len(anchors) == 4 and len(linearised) == 2
    assert anchors[2] is linearised[0] and anchors[3] is linearised[1]
    assert all(a is not p for a in anchors[:2] for p in linearised)
    distilled = [r for r in records if isinstance(r, DistillRecord)]
    assert [r.iteration for r in distilled] == [0, 1]
    assert all(r.distill_rows == 2 * 2 * task.T for r in distilled)  # every sample, both conditions
    assert [e.rollouts for e in summary] == [4, 4]
    assert ReplayBuffer(folder.replay_path).conditions() == [0, 1]


def test_mdgps_fixes_its_sampling_and_anchor_and_needs_the_replay(tmp_path: Path) -> None:
    config = method_config("batch", StreamConfig(alpha=0.5, cstep_anchor="previous"))
    assert (config.alpha, config.alpha_schedule, config.cstep_anchor) == (0.0, "constant", "pre")
    task = PegTask(TaskConfig(urdf="robots/kuka_peg.urdf"), n_worlds=1)
    with pytest.raises(LolgpsError, match="replay"):
        make_learner("batch", task, StreamConfig(replay=False), RunFolder(tmp_path), print)
    task.close()
