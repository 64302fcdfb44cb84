"""Export a run folder's replay as a self-describing HDF5 dataset or as a Minari dataset, and
load the HDF5 dataset back as torch tensors. The schema is documented in ``datasets/README.md``.

A run folder (made by ``scripts/run_stream.py``) holds ``config.json`` and ``replay.h5`` (the
successful trajectories ``D_g`` of every condition, see :mod:`lolgps_torch.data.replay`). The
export flattens the conditions into one sample-first table ``[N, T, ...]`` of trajectories and
adds what a user needs without this package's run folder: the URDF text, joint names, state
layout, time step, cost weights and hole position of every condition.

Both exports write under a temporary name next to the output and rename it into place when
complete, so an interrupted export never leaves anything at the output path. One writer per
output: a stale temporary from a crash is replaced by the next export.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple

import h5py
import numpy as np
import torch
from torch import Tensor

import lolgps_torch
from lolgps_torch.data.replay import FORMAT as REPLAY_FORMAT
from lolgps_torch.data.replay import VERSION as REPLAY_VERSION
from lolgps_torch.data.replay import ConditionRecord, ReplayBuffer, fsync_path
from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import ArmSpec, load_arm
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import place_task
from lolgps_torch.state import StateLayout
from lolgps_torch.task import TaskConfig, task_config_from_dict

FORMAT = "lolgps_torch.dataset"
SCHEMA_VERSION = 1
CONFIG_FILE = "config.json"
SUMMARY_FILE = "summary.json"
REPLAY_FILE = "replay.h5"
EVAL_ROLLOUTS_FILE = "eval_rollouts.h5"
TRAJECTORIES = "trajectories"
CONDITIONS = "conditions"
EVAL = "eval"
# Groups whose attributes hold the metadata (the root's are written separately).
META_GROUPS = ("arm", "state", "task", "cost")
# Root attributes stored as JSON text.
JSON_ATTRS = ("run_config", "run_summary")


class ExportedTrajectories(NamedTuple):
    """The trajectories of a dataset, sample-first (N trajectories of T steps).

    states ``[N, T, dX]`` and actions ``[N, T, dU]`` (float64; units in datasets/README.md),
    cost ``[N, T]`` per-step cost l(x_t, u_t), total_cost ``[N]`` its sum over t,
    final_distance ``[N]`` tip-to-target distance after the last action (m), success ``[N]``
    bool, condition ``[N]`` int64 index, hole_offset ``[N, 2]`` the condition's (dx, dy) (m),
    mean_cur / mean_pre ``[N, T, dU]`` and prec_cur / prec_pre ``[N, T, dU, dU]`` the means and
    precisions of p_cur / p_pre at the states (zeros where has_pre ``[N]`` is false).
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


class _Run(NamedTuple):
    """A run folder read for export: trajectories, per-condition table and metadata groups."""

    trajectories: ExportedTrajectories
    conditions: dict[str, np.ndarray]
    root: dict[str, Any]
    meta: dict[str, dict[str, Any]]


def _one_line(error: BaseException) -> str:
    text = str(error.args[0] if error.args else error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _read_json(path: Path) -> Any:
    try:
        with open(path) as fh:
            return json.load(fh)
    except (OSError, ValueError) as error:
        raise LolgpsError(f"cannot read {path}: {_one_line(error)}") from error


def _read_config(path: Path) -> tuple[dict[str, Any], TaskConfig]:
    """The run's config.json and the task configuration in it."""
    config = _read_json(path)
    if not isinstance(config, dict) or not {"method", "seed", "task"} <= config.keys():
        raise LolgpsError(f"{path}: expected a run configuration with method, seed and task")
    try:
        return config, task_config_from_dict(config["task"])
    except (KeyError, TypeError) as error:
        raise LolgpsError(f"{path}: no valid run configuration ({_one_line(error)})") from error


def _find_urdf(urdf: str, run_dir: Path) -> str:
    """The run's URDF: as saved (absolute, or relative to the current folder), else relative to
    the run folder."""
    for candidate in (Path(urdf), run_dir / urdf):
        if candidate.is_file():
            return str(candidate)
    raise LolgpsError(
        f"URDF {urdf} of run {run_dir} not found in the current folder or the run folder; "
        "export from the folder the run was started in"
    )


def _read_replay(path: Path) -> list[ConditionRecord]:
    if not path.is_file():
        raise LolgpsError(f"{path} not found: the run has no replay")
    try:
        with h5py.File(path, "r") as f:
            fmt, version = f.attrs.get("format"), f.attrs.get("version")
    except OSError as error:
        raise LolgpsError(f"cannot read replay {path}: {_one_line(error)}") from error
    if fmt != REPLAY_FORMAT or version != REPLAY_VERSION:
        raise LolgpsError(
            f"{path} is not a version {REPLAY_VERSION} lolgps_torch replay "
            f"(format {fmt!r}, version {version!r})"
        )
    replay = ReplayBuffer(path)
    return [replay.read_condition(index) for index in replay.conditions()]


def _flatten(records: list[ConditionRecord], threshold: float) -> ExportedTrajectories:
    """Concatenate the conditions' samples into one trajectory table."""
    samples = [r.samples for r in records]
    counts = torch.tensor([s.x.shape[0] for s in samples])
    if int(counts.sum()) == 0:
        raise LolgpsError("the run's replay holds no trajectories")
    offsets = torch.tensor([r.offset for r in records], dtype=torch.float64)
    final = torch.cat([s.final_distance for s in samples])
    return ExportedTrajectories(
        states=torch.cat([s.x for s in samples]),
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
    layout = StateLayout(arm.dof)
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


def _read_run(run_dir: str | Path) -> _Run:
    """Everything the exports write, read from a run folder; bad input -> LolgpsError."""
    run = Path(run_dir)
    if not run.is_dir():
        raise LolgpsError(f"run folder {run} not found")
    config, task = _read_config(run / CONFIG_FILE)
    summary = _read_json(run / SUMMARY_FILE) if (run / SUMMARY_FILE).is_file() else None
    records = _read_replay(run / REPLAY_FILE)
    arm = load_arm(_find_urdf(task.urdf, run), task.ee_link, task.peg)
    geometry = place_task(arm, PegKinematics(arm, "cpu"), task.placement)
    mouth = torch.tensor(geometry.nominal_mouth, dtype=torch.float64)

    trajectories = _flatten(records, task.world.success_threshold)
    T, dX = trajectories.states.shape[1:]
    if task.world.T != T or StateLayout(arm.dof).dX != dX:
        raise LolgpsError(
            f"replay of {run} holds T={T}, dX={dX}; its configuration and arm give "
            f"T={task.world.T}, dX={StateLayout(arm.dof).dX}"
        )
    offsets = np.array([r.offset for r in records], dtype=np.float64).reshape(-1, 2)
    conditions = {
        "index": np.array([r.condition for r in records], dtype=np.int64),
        "hole_offset": offsets,
        "hole_mouth": mouth.numpy() + np.pad(offsets, ((0, 0), (0, 1))),
        "iterations": np.array([r.iterations for r in records], dtype=np.int64),
        "n_trajectories": np.array([r.samples.x.shape[0] for r in records], dtype=np.int64),
    }
    root = {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "lolgps_torch_version": lolgps_torch.__version__,
        "method": config["method"],
        "seed": config["seed"],
        "run_config": config,
        "run_summary": summary,
    }
    return _Run(trajectories, conditions, root, _metadata(task, arm, mouth, geometry.q0))


def _check_output(out: Path, force: bool) -> None:
    if out.exists() and not force:
        raise LolgpsError(f"{out} already exists; pass --force (force=True) to overwrite it")


def _to_attr(key: str, value: Any) -> Any:
    """A metadata value as an HDF5 attribute: JSON text for ``JSON_ATTRS``, lists as arrays."""
    if key in JSON_ATTRS:
        return json.dumps(value)
    if isinstance(value, list):
        array = np.asarray(value)
        return array.astype(h5py.string_dtype()) if array.dtype.kind == "U" else array
    return value


def _from_attr(key: str, value: Any) -> Any:
    """Inverse of :func:`_to_attr` to plain Python values."""
    if key in JSON_ATTRS:
        return json.loads(value)
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value


def _write_attrs(obj: h5py.Group, values: dict[str, Any]) -> None:
    for key, value in values.items():
        if value is not None:
            obj.attrs[key] = _to_attr(key, value)


def _write_dataset(group: h5py.Group, name: str, array: np.ndarray) -> None:
    """Chunked per trajectory (first axis), shuffled, gzip-compressed and checksummed."""
    group.create_dataset(
        name,
        data=array,
        chunks=(1, *array.shape[1:]) if array.ndim > 1 else True,
        maxshape=(None, *array.shape[1:]),
        compression="gzip",
        shuffle=True,
        fletcher32=True,
    )


def _copy_eval(f: h5py.File, path: Path) -> None:
    """Copy the evaluation rollouts file verbatim into the group ``/eval``."""
    group = f.create_group(EVAL)
    try:
        with h5py.File(path, "r") as src:
            for key, value in src.attrs.items():
                group.attrs[key] = value
            for name in src:
                src.copy(src[name], group, name=name)
    except (OSError, KeyError) as error:
        raise LolgpsError(f"cannot read {path}: {_one_line(error)}") from error
    group.attrs["source_file"] = EVAL_ROLLOUTS_FILE


def _write_hdf5(tmp: Path, run: _Run, eval_path: Path | None) -> None:
    with h5py.File(tmp, "w", libver="v110") as f:
        _write_attrs(f, run.root)
        for name in META_GROUPS:
            _write_attrs(f.create_group(name), run.meta[name])
        table = f.create_group(CONDITIONS)
        for name, array in run.conditions.items():
            _write_dataset(table, name, array)
        group = f.create_group(TRAJECTORIES)
        for name, tensor in run.trajectories._asdict().items():
            _write_dataset(group, name, tensor.numpy())
        if eval_path is not None:
            _copy_eval(f, eval_path)


def export_hdf5(
    run_dir: str | Path, out_path: str | Path, force: bool = False, include_eval: bool = False
) -> ExportReport:
    """Write the run's trajectories and metadata to one HDF5 file (schema in datasets/README.md).

    :param run_dir: a run folder made by ``scripts/run_stream.py``.
    :param out_path: the HDF5 file to write.
    :param force: overwrite an existing ``out_path``.
    :param include_eval: also copy the run's ``eval_rollouts.h5`` verbatim into ``/eval``
        (an error if the run has none).
    :returns: what was written.
    """
    start = time.perf_counter()
    out = Path(out_path)
    _check_output(out, force)
    run = _read_run(run_dir)
    eval_path = Path(run_dir) / EVAL_ROLLOUTS_FILE if include_eval else None
    if eval_path is not None and not eval_path.is_file():
        raise LolgpsError(f"--include-eval: {eval_path} not found (the run saved no eval rollouts)")
    tmp = out.with_name(out.name + ".partial")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _write_hdf5(tmp, run, eval_path)
        fsync_path(tmp)
        os.replace(tmp, out)
        fsync_path(out.parent)
    except OSError as error:
        raise LolgpsError(f"cannot write {out}: {_one_line(error)}") from error
    finally:
        tmp.unlink(missing_ok=True)
    N, T = run.trajectories.cost.shape
    return ExportReport(out, N, N * T, out.stat().st_size, time.perf_counter() - start)


@contextmanager
def _open_dataset(path: Path) -> Iterator[h5py.File]:
    """Open an exported dataset and check its format and schema version; HDF5 failures (a
    truncated or corrupt file, a missing object) -> LolgpsError."""
    if not path.is_file():
        raise LolgpsError(f"dataset {path} not found")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise LolgpsError(f"{path} is not a lolgps_torch dataset")
            version = f.attrs.get("schema_version")
            if version != SCHEMA_VERSION:
                raise LolgpsError(
                    f"{path} has schema version {version}; this lolgps_torch "
                    f"({lolgps_torch.__version__}) reads schema version {SCHEMA_VERSION}"
                )
            yield f
    except (OSError, KeyError, ValueError) as error:
        raise LolgpsError(f"cannot read dataset {path}: {_one_line(error)}") from error


def _read_metadata(f: h5py.File) -> dict[str, Any]:
    meta: dict[str, Any] = {k: _from_attr(k, v) for k, v in f.attrs.items()}
    meta.setdefault("run_summary", None)
    for name in META_GROUPS:
        meta[name] = {k: _from_attr(k, v) for k, v in f[name].attrs.items()}
    table = {k: ds[()] for k, ds in f[CONDITIONS].items()}
    meta[CONDITIONS] = [
        {k: table[k][i].tolist() for k in table} for i in range(len(table["index"]))
    ]
    meta["has_eval"] = EVAL in f
    return meta


def _select_rows(
    f: h5py.File, conditions: list[int] | None, success_only: bool, path: Path
) -> np.ndarray:
    """Indices of the trajectories of the given conditions (and successful, if asked)."""
    group = f[TRAJECTORIES]
    keep = np.ones(group["condition"].shape[0], dtype=bool)
    if conditions is not None:
        stored = f[CONDITIONS]["index"][()]
        missing = sorted(set(conditions) - set(stored.tolist()))
        if missing:
            raise LolgpsError(
                f"dataset {path} holds no condition {missing[0]} "
                f"(it holds {', '.join(str(c) for c in stored)})"
            )
        keep &= np.isin(group["condition"][()], conditions)
    if success_only:
        keep &= group["success"][()]
    return np.flatnonzero(keep)


def load_dataset(
    path: str | Path,
    conditions: list[int] | None = None,
    success_only: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[ExportedTrajectories, dict[str, Any]]:
    """Load an HDF5 dataset written by :func:`export_hdf5`.

    :param path: the dataset file.
    :param conditions: keep only the trajectories of these condition indices (default: all).
    :param success_only: keep only successful trajectories.
    :param device: torch device of the returned tensors.
    :returns: the trajectories (stored order) and the metadata: the root attributes
        (``run_config`` and ``run_summary`` parsed from JSON), one dict per metadata group
        (``arm``, ``state``, ``task``, ``cost``), ``conditions`` (one dict per condition) and
        ``has_eval``.
    """
    file = Path(path)
    with _open_dataset(file) as f:
        rows = _select_rows(f, conditions, success_only, file)
        group = f[TRAJECTORIES]
        complete = len(rows) == group["condition"].shape[0]
        tensors = {
            name: torch.from_numpy(group[name][()] if complete else group[name][rows]).to(device)
            for name in ExportedTrajectories._fields
        }
        return ExportedTrajectories(**tensors), _read_metadata(f)


@contextmanager
def _minari_root(root: Path) -> Iterator[None]:
    """Point Minari's ``MINARI_DATASETS_PATH`` at ``root`` for the duration (not thread-safe)."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def _check_minari_name(name: str) -> None:
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        parse_dataset_id(name)
    except (ValueError, TypeError):
        raise LolgpsError(
            f"Minari dataset folder name {name!r} must be a dataset id NAME-vVERSION, "
            "e.g. peg-insertion-lolgps-v0"
        ) from None


def _write_minari(name: str, run: _Run) -> None:
    """Create the Minari dataset ``name`` under the current ``MINARI_DATASETS_PATH``."""
    import gymnasium as gym
    import minari
    from minari.data_collector import EpisodeBuffer

    tr = run.trajectories
    N, T = tr.cost.shape
    states, actions, rewards = tr.states.numpy(), tr.actions.numpy(), (-tr.cost).numpy()
    # The state's tip block is p_tip - p*_tip: its norm is the env's info "tip_distance".
    tip = slice(*run.meta["state"]["points"])
    tip_distance = np.linalg.norm(states[:, :, tip][:, :, :3], axis=-1)  # [N, T]
    success = tip_distance < run.meta["task"]["success_threshold"]
    truncations = np.zeros(T - 1, dtype=bool)
    truncations[-1] = True
    buffers = [
        EpisodeBuffer(
            id=i,
            options={"hole_offset": tr.hole_offset[i].tolist()},
            observations=states[i],
            actions=actions[i, :-1],
            rewards=rewards[i, :-1],
            terminations=np.zeros(T - 1, dtype=bool),
            truncations=truncations,
            infos={"tip_distance": tip_distance[i], "success": success[i]},
        )
        for i in range(N)
    ]
    effort = np.asarray(run.meta["arm"]["effort"], dtype=np.float64)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=UserWarning, module=r"minari\.")
        dataset = minari.create_dataset_from_buffers(
            dataset_id=name,
            buffer=buffers,
            observation_space=gym.spaces.Box(-np.inf, np.inf, (states.shape[-1],), np.float64),
            action_space=gym.spaces.Box(-effort, effort, dtype=np.float64),
            algorithm_name=f"lolgps_torch {run.root['method']}",
            description=(
                "Successful peg-insertion trajectories of a lolgps_torch run: observations are "
                "the states x_0..x_{T-1}, actions the torques u_0..u_{T-2} (the last action is "
                "dropped: the replay holds no state after it), rewards -l(x_t, u_t). "
                "See metadata['lolgps_torch'] and datasets/README.md."
            ),
            data_format="hdf5",
        )
    dataset.storage.update_episode_metadata(
        {
            "condition": int(tr.condition[i]),
            "success": bool(tr.success[i]),
            "final_distance": float(tr.final_distance[i]),
            "total_cost": float(tr.total_cost[i]),
        }
        for i in range(N)
    )
    conditions = {k: v.tolist() for k, v in run.conditions.items()}
    dataset.storage.update_metadata(
        {"lolgps_torch": {**run.root, **run.meta, CONDITIONS: conditions}}
    )


def _tree_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _fsync_tree(path: Path) -> None:
    for p in sorted(path.rglob("*"), reverse=True):
        fsync_path(p)
    fsync_path(path)


def export_minari(run_dir: str | Path, out_dir: str | Path, force: bool = False) -> ExportReport:
    """Write the run's trajectories as a Minari dataset (HDF5 storage) in folder ``out_dir``.

    The folder's name is the dataset id (``NAME-vVERSION``, no namespace) and its parent is the
    datasets root: load it with ``MINARI_DATASETS_PATH=<parent>`` and
    ``minari.load_dataset(<name>)``. One episode per trajectory: observations are the T stored
    states, actions and rewards (``-cost``) the first T-1 steps, since the replay holds no state
    after the last action; the last step is a truncation. Per-episode metadata (condition,
    success, final_distance, total_cost over all T steps) and the reset option ``hole_offset``
    are stored with each episode; the dataset metadata key ``lolgps_torch`` holds the schema's
    metadata.

    :param run_dir: a run folder made by ``scripts/run_stream.py``.
    :param out_dir: the dataset folder to create (``<datasets root>/<dataset id>``).
    :param force: replace an existing ``out_dir``.
    :returns: what was written (steps are the T-1 transitions per episode).
    """
    start = time.perf_counter()
    out = Path(out_dir)
    try:
        import minari  # noqa: F401
    except ImportError:
        raise LolgpsError(
            "the Minari export needs the minari package: pip install 'lolgps_torch[minari]'"
        ) from None
    _check_minari_name(out.name)
    _check_output(out, force)
    run = _read_run(run_dir)
    N, T = run.trajectories.cost.shape
    if T < 2:
        raise LolgpsError(f"a Minari episode needs T >= 2 stored states, the run has T={T}")
    staging = out.with_name(f".{out.name}.partial")
    retired = out.with_name(f".{out.name}.old")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        with _minari_root(staging):
            _write_minari(out.name, run)
        _fsync_tree(staging / out.name)
        if out.exists():
            shutil.rmtree(retired, ignore_errors=True)
            os.replace(out, retired)
        os.replace(staging / out.name, out)
        fsync_path(out.parent)
    except (OSError, ValueError) as error:
        raise LolgpsError(f"cannot write Minari dataset {out}: {_one_line(error)}") from error
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(retired, ignore_errors=True)
    return ExportReport(out, N, N * (T - 1), _tree_size(out), time.perf_counter() - start)
