"""A finished (or interrupted) run, loaded: what the research tools and the exports read back
from a run folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.replay import ConditionRecord, ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder, RunInfo
from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.task import PegTask


@dataclass(frozen=True)
class LoadedRun:
    """A run folder's configuration, replay and policies.

    :param folder: the run folder.
    :param info: its checked config.json, with the task built on the folder's URDF copy.
    :param replay: its replay D_g.
    :param records: every completed condition's replay group, in stream order.
    :param device: where policies are loaded.
    """

    folder: RunFolder
    info: RunInfo
    replay: ReplayBuffer
    records: list[ConditionRecord]
    device: torch.device

    def make_task(self, n_worlds: int = 5) -> PegTask:
        """The run's task with ``n_worlds`` worlds (the caller closes it)."""
        return PegTask(self.info.task, n_worlds=n_worlds, device=str(self.device))

    def policy(self, condition: int | None = None) -> GaussianPolicy:
        """The global policy checkpointed after ``condition`` (default: the last completed
        condition's)."""
        if condition is None:
            condition = self.records[-1].condition
        return load_policy(self.folder.checkpoint_dir(condition), self.device)


def load_run(path: str | Path, device: torch.device | str = "cpu") -> LoadedRun:
    """Read the run folder at ``path``: its config.json and the replay of every completed
    condition; a folder without completed conditions is a :class:`LolgpsError`."""
    folder = RunFolder(path)
    info = folder.read_run()
    replay = ReplayBuffer(folder.replay_path)
    records = [replay.read_condition(i) for i in replay.conditions()]
    if not records:
        raise LolgpsError(f"{folder.replay_path}: the run completed no condition")
    return LoadedRun(folder, info, replay, records, torch.device(device))
