"""A finished (or interrupted) run, read back from its run folder: config.json checked into a
:class:`RunInfo` (with the stream's settings as a :class:`StreamConfig`), and the replay and
policies the research tools and the evaluation load."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from lolgps_torch.configs import from_dict
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.replay import ConditionRecord, ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.stream import StreamConfig
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.sim.franka import SIMULATED, RealArmConfig
from lolgps_torch.task import PegTask, TaskConfig

Position = tuple[float, float]


@dataclass(frozen=True)
class RunInfo:
    """What a run's config.json says, checked.

    :param task: the task, built from the run folder's URDF copy (the recorded path for runs
        made before runs kept one).
    :param conditions: the hole offsets ``(dx, dy)`` (m) in stream order.
    :param stages: ``{"name", "last_condition"}`` per training stage, in order.
    :param stream: the stream's settings (those a run saved before a setting existed take
        its default).
    """

    task: TaskConfig
    conditions: list[Position]
    stages: list[dict[str, Any]]
    method: str
    seed: int
    stream: StreamConfig

    def check_conditions(self, indices: Sequence[int]) -> None:
        """A :class:`LolgpsError` unless every index names one of the run's conditions."""
        bad = [c for c in indices if not 0 <= c < len(self.conditions)]
        if bad:
            raise LolgpsError(f"conditions {bad} not in the run's {len(self.conditions)}")


def stream_config(folder: RunFolder, config: dict[str, Any]) -> StreamConfig:
    """The :class:`StreamConfig` of ``config`` (``folder``'s config.json) from its ``stream``
    (``asdict`` of one; the defaults without it); an unknown or invalid setting is a
    :class:`LolgpsError` naming config.json."""
    saved = config.get("stream", {})
    try:
        if not isinstance(saved, dict):
            raise TypeError(f"not a JSON object: {saved!r}")
        return from_dict(StreamConfig, saved)
    except (LolgpsError, ValueError, TypeError, AttributeError) as error:
        raise LolgpsError(f"corrupt {folder.config_path}: stream: {error}") from None


def read_run(folder: RunFolder) -> RunInfo:
    """``folder``'s config.json, checked: a missing folder or file, a malformed entry, a
    stream setting :class:`StreamConfig` does not know or rejects, or stages that do not end
    at increasing conditions are a :class:`LolgpsError`."""
    if not folder.path.is_dir():
        raise LolgpsError(f"run folder not found: {folder.path}")
    config = folder.read_config()
    try:
        conditions = [(float(dx), float(dy)) for dx, dy in config["conditions"]]
        stages: list[dict[str, Any]] = [
            {"name": str(s["name"]), "last_condition": int(s["last_condition"])}
            for s in config["stages"]
        ]
        info = RunInfo(
            folder.task_config(config["task"]),
            conditions,
            stages,
            str(config["method"]),
            int(config["seed"]),
            stream_config(folder, config),
        )
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        raise LolgpsError(
            f"corrupt {folder.config_path}: {type(error).__name__}: {error}"
        ) from None
    lasts = [s["last_condition"] for s in stages]
    if not lasts or lasts != sorted(set(lasts)) or not 0 <= lasts[-1] < len(conditions):
        raise LolgpsError(
            f"corrupt {folder.config_path}: stages must end at increasing conditions below "
            f"{len(conditions)}, got last_condition {lasts}"
        )
    return info


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

    def make_task(self, n_worlds: int = 5, real: RealArmConfig = SIMULATED) -> PegTask:
        """The run's task with ``n_worlds`` worlds, or on the real arm ``real`` (the caller
        closes it)."""
        return PegTask(self.info.task, n_worlds=n_worlds, device=str(self.device), real=real)

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
    info = read_run(folder)
    replay = ReplayBuffer(folder.replay_path)
    records = [replay.read_condition(i) for i in replay.conditions()]
    if not records:
        raise LolgpsError(f"{folder.replay_path}: the run completed no condition")
    return LoadedRun(folder, info, replay, records, torch.device(device))
