"""A run folder read for export: its replay flattened into one trajectory table, and the
metadata a dataset needs without this package's run folder (schema: ``datasets/README.md``).

A run folder (made by ``scripts/run_stream.py``) holds ``config.json``, ``replay.h5`` (the
successful trajectories ``D_g`` of every condition, see :mod:`lolgps_torch.data.replay`) and,
for runs made since it kept one, ``arm.urdf``. The exports (:mod:`~lolgps_torch.data.export_hdf5`,
:mod:`~lolgps_torch.data.export_minari`) write what :func:`read_run` returns.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import h5py
import numpy as np
import torch
from torch import Tensor

import lolgps_torch
from lolgps_torch.data.replay import FORMAT as REPLAY_FORMAT
from lolgps_torch.data.replay import VERSION as REPLAY_VERSION
from lolgps_torch.data.replay import ConditionRecord, ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder, fsync_path, read_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.progress import progress
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import place_task
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.task import TaskConfig, load_task_arm
from lolgps_torch.types import VisitedRows

FORMAT = "lolgps_torch.dataset"
# Version 2 holds the T+1 states of each trajectory; version 1 held the first T.
SCHEMA_VERSION = 2
READABLE_SCHEMA_VERSIONS = (1, 2)
CONDITIONS = "conditions"


class ExportedTrajectories(NamedTuple):
    """The trajectories of a dataset, sample-first (N trajectories of T actions).

    states ``[N, T+1, dX]`` (``x_0 .. x_T``, ``x_T`` after the last action; ``[N, T, dX]`` in
    schema-1 files) and actions ``[N, T, dU]`` (float64; units in datasets/README.md), cost
    ``[N, T]`` per-step cost l(x_t, u_t), total_cost ``[N]`` its sum over t, final_distance
    ``[N]`` tip-to-target distance after the last action (m), success ``[N]`` bool, condition
    ``[N]`` int64 index, hole_offset ``[N, 2]`` the condition's (dx, dy) (m), mean_cur /
    mean_pre ``[N, T, dU]`` and prec_cur / prec_pre ``[N, T, dU, dU]`` the means and
    precisions of p_cur / p_pre at the states ``x_0 .. x_{T-1}`` (zeros where has_pre ``[N]``
    is false).
    """

    states: Tensor
    actions: Tensor
    cost: Tensor
    total_cost: Tensor
    final_distance: Tensor
    success: Tensor
    condition: Tensor
    hole_offset: Tensor
    mean_cur: Tensor
    prec_cur: Tensor
    mean_pre: Tensor
    prec_pre: Tensor
    has_pre: Tensor


@dataclass(frozen=True)
class ExportReport:
    """What an export wrote: the output path, trajectories (episodes), steps (transitions),
    size on disk (bytes) and wall time (s)."""

    path: Path
    trajectories: int
    steps: int
    bytes: int
    seconds: float

    @property
    def megabytes(self) -> float:
        return self.bytes / 1e6


class RunData(NamedTuple):
    """A run folder read for export: trajectories, per-condition table, root attributes,
    metadata groups (``arm``, ``state``, ``task``, ``cost``), the task, its URDF an
    absolute path (the run folder's copy where it has one), and the labelled states the
    policy visited in its S-steps, by field (empty: none)."""

    trajectories: ExportedTrajectories
    conditions: dict[str, np.ndarray]
    root: dict[str, Any]
    meta: dict[str, dict[str, Any]]
    task: TaskConfig
    visited: dict[str, np.ndarray]


def one_line(error: BaseException) -> str:
    """The first line of an exception's message (its type's name if it has none)."""
    text = str(error.args[0] if error.args else error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def check_output(out: Path, force: bool) -> None:
    if out.exists() and not force:
        raise LolgpsError(f"{out} already exists; pass --force (force=True) to overwrite it")


def _find_urdf(urdf: str, run_dir: Path) -> str:
    """The URDF as an absolute path: as given (absolute, or relative to the current folder),
    else relative to the run folder."""
    for candidate in (Path(urdf), run_dir / urdf):
        if candidate.is_file():
            return str(candidate.resolve())
    raise LolgpsError(
        f"URDF {urdf} of run {run_dir} not found in the current folder or the run folder; "
        "export from the folder the run was started in"
    )


def _read_config(folder: RunFolder) -> tuple[dict[str, Any], TaskConfig]:
    """The run's config.json and its task, built on the folder's URDF copy if it has one."""
    config = folder.read_config()
    if not {"method", "seed", "task"} <= config.keys():
        raise LolgpsError(
            f"{folder.config_path}: expected a run configuration with method, seed and task"
        )
    try:
        task = folder.task_config(config["task"])
    except (KeyError, TypeError) as error:
        raise LolgpsError(
            f"{folder.config_path}: no valid run configuration ({one_line(error)})"
        ) from error
    return config, replace(task, urdf=_find_urdf(task.urdf, folder.path))


def _read_replay(replay: ReplayBuffer) -> list[ConditionRecord]:
    """Every condition of a replay of this version, which must hold the final states."""
    path = replay.path
    if not path.is_file():
        raise LolgpsError(f"{path} not found: the run has no replay")
    try:
        with h5py.File(path, "r") as f:
            fmt, version = f.attrs.get("format"), f.attrs.get("version")
    except OSError as error:
        raise LolgpsError(f"cannot read replay {path}: {one_line(error)}") from error
    if fmt != REPLAY_FORMAT or version != REPLAY_VERSION:
        raise LolgpsError(
            f"{path} is not a version {REPLAY_VERSION} lolgps_torch replay "
            f"(format {fmt!r}, version {version!r})"
        )
    indices = replay.conditions()
    records = [replay.read_condition(i) for i in progress(indices, len(indices), "replay")]
    if any(r.samples.final_state is None for r in records):
        raise LolgpsError(
            f"{path} was written before replays kept the state after the last action; "
            "a dataset needs all T+1 states of a trajectory"
        )
    return records


def _flatten(records: list[ConditionRecord], threshold: float) -> ExportedTrajectories:
    """Concatenate the conditions' samples into one trajectory table."""
    samples = [r.samples for r in records]
    counts = torch.tensor([s.x.shape[0] for s in samples])
    if int(counts.sum()) == 0:
        raise LolgpsError("the run's replay holds no trajectories")
    offsets = torch.tensor([r.offset for r in records], dtype=torch.float64)
    final = torch.cat([s.final_distance for s in samples])
    last = [s.final_state for s in samples if s.final_state is not None]
    return ExportedTrajectories(
        states=torch.cat(
            [torch.cat([s.x, f[:, None]], 1) for s, f in zip(samples, last, strict=True)]
        ),
        actions=torch.cat([s.u for s in samples]),
        cost=torch.cat([s.cost for s in samples]),
        total_cost=torch.cat([s.cost.sum(-1) for s in samples]),
        final_distance=final,
        success=final < threshold,
        condition=torch.tensor([r.condition for r in records]).repeat_interleave(counts),
        hole_offset=offsets.repeat_interleave(counts, dim=0),
        mean_cur=torch.cat([s.mean_cur for s in samples]),
        prec_cur=torch.cat([s.prec_cur for s in samples]),
        mean_pre=torch.cat([s.mean_pre for s in samples]),
        prec_pre=torch.cat([s.prec_pre for s in samples]),
        has_pre=torch.cat([s.has_pre for s in samples]),
    )


def _metadata(
    task: TaskConfig, arm: ArmSpec, mouth: Tensor, q0: tuple[float, ...]
) -> dict[str, dict[str, Any]]:
    """The metadata groups ``arm``, ``state``, ``task`` and ``cost`` (plain JSON-able values)."""
    layout = task.world.layout(arm.dof)
    return {
        "arm": {
            "urdf_text": arm.urdf_text,
            "urdf_sha256": hashlib.sha256(arm.urdf_text.encode()).hexdigest(),
            "source_urdf_path": arm.source_path,
            "source_urdf_sha256": arm.source_sha256,
            "joint_names": list(arm.joint_names),
            "ee_link": arm.ee_link,
            "point_link": arm.point_link,
            "effort": list(arm.effort),
            "joint_lower": list(arm.lower),
            "joint_upper": list(arm.upper),
            "q0": list(q0),
            "nominal_hole_mouth": mouth.tolist(),
        },
        "state": {"dX": layout.dX, "dU": layout.dU, "names": layout.names(), **layout.as_dict()},
        "task": {
            "dt": task.world.dt,
            "substeps": task.world.substeps,
            "T": task.world.T,
            "success_threshold": task.world.success_threshold,
            "hole_depth": task.world.depth,
        },
        "cost": asdict(task.cost),
    }


def _conditions(records: list[ConditionRecord], mouth: Tensor) -> dict[str, np.ndarray]:
    """The per-condition table: index, hole offset and mouth, iterations, trajectory count."""
    offsets = np.array([r.offset for r in records], dtype=np.float64).reshape(-1, 2)
    return {
        "index": np.array([r.condition for r in records], dtype=np.int64),
        "hole_offset": offsets,
        "hole_mouth": mouth.numpy() + np.pad(offsets, ((0, 0), (0, 1))),
        "iterations": np.array([r.iterations for r in records], dtype=np.int64),
        "n_trajectories": np.array([r.samples.x.shape[0] for r in records], dtype=np.int64),
    }


def read_run(run_dir: str | Path) -> RunData:
    """Everything the exports write, read from a run folder; bad input -> LolgpsError."""
    folder = RunFolder(run_dir)
    if not folder.path.is_dir():
        raise LolgpsError(f"run folder {folder.path} not found")
    config, task = _read_config(folder)
    summary = read_json(folder.summary_path) if folder.summary_path.is_file() else None
    records = _read_replay(ReplayBuffer(folder.replay_path))
    arm = load_task_arm(task)
    geometry = place_task(arm, PegKinematics(arm, "cpu"), task.placement, task.world.depth)
    mouth = torch.tensor(geometry.nominal_mouth, dtype=torch.float64)
    trajectories = _flatten(records, task.world.success_threshold)
    T, dX = trajectories.actions.shape[1], trajectories.states.shape[2]
    expected = task.world.layout(arm.dof).dX
    if task.world.T != T or expected != dX:
        raise LolgpsError(
            f"replay of {folder.path} holds T={T}, dX={dX}; its configuration and arm give "
            f"T={task.world.T}, dX={expected}"
        )
    root = {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "lolgps_torch_version": lolgps_torch.__version__,
        "method": config["method"],
        "seed": config["seed"],
        "run_config": config,
        "run_summary": summary,
    }
    meta = _metadata(task, arm, mouth, geometry.q0)
    return RunData(trajectories, _conditions(records, mouth), root, meta, task, _visited(records))


def _visited(records: list[ConditionRecord]) -> dict[str, np.ndarray]:
    """Every condition's visited rows, in stream order, by field: ``states``, the label
    fields, ``condition`` (whose controllers labelled the row) and ``t`` (empty: none)."""
    parts = [r.visited for r in records if r.visited is not None]
    if not parts:
        return {}
    rows = VisitedRows.cat(parts)
    fields = {
        "states": rows.rows.x,
        **rows.rows._asdict(),
        "condition": rows.condition,
        "t": rows.t,
    }
    del fields["x"]
    return {name: tensor.cpu().numpy() for name, tensor in fields.items()}


def tip_distances(run: RunData) -> np.ndarray:
    """The tip's distance to its target (m) at each of the T+1 states of every trajectory,
    ``[N, T+1]``: the norm of the state's tip block ``p_tip - p*_tip``."""
    tip = slice(*run.meta["state"]["points"])
    return np.linalg.norm(run.trajectories.states.numpy()[:, :, tip][:, :, :3], axis=-1)


def tree_size(path: Path) -> int:
    """The bytes of the files under the folder ``path``."""
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def fsync_tree(path: Path) -> None:
    """Flush the folder ``path`` and everything under it to disk."""
    for p in sorted(path.rglob("*"), reverse=True):
        fsync_path(p)
    fsync_path(path)


def move_into_place(staged: Path, out: Path) -> None:
    """Replace the folder ``out`` (if any) by the folder ``staged``."""
    retired = out.with_name(f".{out.name}.old")
    try:
        if out.exists():
            shutil.rmtree(retired, ignore_errors=True)
            os.replace(out, retired)
        os.replace(staged, out)
        fsync_path(out.parent)
    finally:
        shutil.rmtree(retired, ignore_errors=True)
