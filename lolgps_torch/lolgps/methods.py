"""The three ways of learning a stream, by name: LOLGPS, naive sequential and batch GPS."""

from __future__ import annotations

from dataclasses import replace
from typing import Literal, Protocol, get_args

from lolgps_torch.data.records import ConditionSummary
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.batch import BatchLearner
from lolgps_torch.lolgps.stream import Log, StreamConfig, StreamLearner
from lolgps_torch.task import PegTask

Method = Literal["lolgps", "naive", "batch"]
METHODS: tuple[str, ...] = get_args(Method)


class Learner(Protocol):
    def run(
        self, conditions: list[tuple[float, float]], on_condition: OnCondition
    ) -> list[ConditionSummary]: ...


class OnCondition(Protocol):
    def __call__(self, entry: ConditionSummary) -> None: ...


def method_config(method: str, config: StreamConfig) -> StreamConfig:
    """``config`` as ``method`` runs it: naive sequential learning has no p_pre (so alpha 0),
    no replay, no transfer and no labelled states of the policy's own; batch GPS (no transfer either) (MDGPS) samples p_cur and anchors its C-step to the
    policy's linearisation; LOLGPS takes it as it is."""
    if method not in METHODS:
        raise LolgpsError(f"method {method!r}: one of {METHODS}")
    if method == "naive":
        return replace(
            config,
            use_pre=False,
            replay=False,
            alpha=0.0,
            transfer="none",
            onpolicy=False,
            onpolicy_rounds=0,
        )
    if method == "batch":  # MDGPS: samples p_cur, C-step anchored to the policy
        return replace(
            config, alpha=0.0, alpha_schedule="constant", cstep_anchor="pre", transfer="none"
        )
    return config


def make_learner(
    method: str, task: PegTask, config: StreamConfig, folder: RunFolder, log: Log
) -> Learner:
    """The learner of ``method`` (with :func:`method_config` applied to ``config``)."""
    config = method_config(method, config)
    if method == "batch":
        return BatchLearner(task, config, folder, log)
    return StreamLearner(task, config, folder, log)
