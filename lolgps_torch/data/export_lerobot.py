"""Export a run folder as a LeRobot dataset (format v3.0), the format LeRobot's loader
(``LeRobotDataset``) and the policies trained on it read. The layout is documented in
``datasets/README.md``.

One episode per successful trajectory of the run's replay D_g, its frames the T control steps
``t = 0 .. T-1`` at ``fps = 1 / dt``: the state ``x_t`` as ``observation.state``, the torques
``u_t`` as ``action``, the step's cost ``l(x_t, u_t)`` as ``cost``, whether the tip is within
the success threshold after the step as ``next.success``, and the episode's last step as
``next.done``; the episode's task is its condition's hole offset (:func:`task_text`). Numbers
are stored as float32, LeRobot's convention. With a camera (``--video``), each episode's
frames ``x_0 .. x_{T-1}`` are filmed as the feature ``observation.images.camera``, all
episodes one after another in one H.264 video.

The files are written with pyarrow and pandas rather than with LeRobot's own writer: that
writer's package (``lerobot-dataset``) imports torchvision, whose Linux wheels in the package
index are CUDA builds that do not import beside a CPU-only torch. The dataset is written in a
staging folder next to the output and renamed into place, so an interrupted export never
leaves anything at the output path.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lolgps_torch.data.dataset import (
    ExportReport,
    RunData,
    check_output,
    fsync_tree,
    move_into_place,
    one_line,
    read_run,
    tip_distances,
    tree_size,
)
from lolgps_torch.errors import LolgpsError

VERSION = "v3.0"  # LeRobot's dataset format
CHUNK_FILE = "chunk-000/file-000"  # each table and the video are one file, the first
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
CAMERA = "observation.images.camera"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
INSTALL = "pip install 'lolgps_torch[lerobot]'"

Film = Callable[[RunData, Sequence[int], Path, int], tuple[int, int]]
"""Films the run's trajectories ``rows`` one after another into the H.264 video at the path,
at the given frames per second, one frame for each state ``x_0 .. x_{T-1}``; returns the
frames' width and height."""


def task_text(offset: Sequence[float]) -> str:
    """An episode's task: its condition's hole offset ``(dx, dy)`` (m) from the nominal hole."""
    dx, dy = (float(v) for v in offset)
    return f"insert the peg into the hole offset by ({dx!r}, {dy!r}) m from the nominal hole"


def frames_per_second(dt: float) -> int:
    """LeRobot's whole frames per second for the control step ``dt`` (s): ``1 / dt``, which
    must be a whole number."""
    fps = round(1.0 / dt)
    if fps < 1 or not math.isclose(fps * dt, 1.0, rel_tol=1e-9):
        raise LolgpsError(
            f"a LeRobot dataset has a whole number of frames per second; the run's control "
            f"step dt = {dt} s gives 1/dt = {1.0 / dt:.6g}"
        )
    return fps


def _episode_tasks(run: RunData, rows: np.ndarray) -> tuple[list[str], list[int]]:
    """The dataset's tasks, in order of first use, and each episode's index among them."""
    texts = [task_text(offset) for offset in run.trajectories.hole_offset[rows].tolist()]
    tasks = list(dict.fromkeys(texts))
    return tasks, [tasks.index(text) for text in texts]


def _columns(run: RunData, rows: np.ndarray, fps: int, task: list[int]) -> dict[str, np.ndarray]:
    """Every frame's value of each feature, the frames of the episodes ``rows`` in order
    (``task``: each episode's task index)."""
    tr = run.trajectories
    T, n = tr.cost.shape[1], len(rows)
    success = tip_distances(run)[rows, 1:] < run.meta["task"]["success_threshold"]
    frame = np.tile(np.arange(T), n)
    return {
        "observation.state": tr.states.numpy()[rows, :T].reshape(n * T, -1).astype(np.float32),
        "action": tr.actions.numpy()[rows].reshape(n * T, -1).astype(np.float32),
        "cost": tr.cost.numpy()[rows].reshape(-1).astype(np.float32),
        "next.success": success.reshape(-1),
        "next.done": frame == T - 1,
        "timestamp": (frame / fps).astype(np.float32),
        "frame_index": frame,
        "episode_index": np.repeat(np.arange(n), T),
        "index": np.arange(n * T),
        "task_index": np.repeat(task, T),
    }


def _features(run: RunData, columns: dict[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """LeRobot's description of each feature: dtype, shape and names."""
    names = {
        "observation.state": run.meta["state"]["names"],
        "action": run.meta["arm"]["joint_names"],
    }
    return {
        key: {"dtype": str(v.dtype), "shape": list(v.shape[1:]) or [1], "names": names.get(key)}
        for key, v in columns.items()
    }


def _stats(values: np.ndarray) -> dict[str, list[Any]]:
    """LeRobot's statistics of one feature's frames, per entry: min, max, mean, std, the
    count of frames and the quantiles :data:`QUANTILES`."""
    x = values.astype(np.float64).reshape(len(values), -1)
    stats = {
        "min": x.min(axis=0),
        "max": x.max(axis=0),
        "mean": x.mean(axis=0),
        "std": x.std(axis=0),
        **{name: np.quantile(x, q, axis=0) for name, q in QUANTILES.items()},
    }
    return {name: value.tolist() for name, value in stats.items()} | {"count": [len(x)]}


def _episodes(run: RunData, rows: np.ndarray, tasks: list[str], task: list[int]) -> dict[str, Any]:
    """The episodes' table: each one's task, length and frames, and the condition it came
    from and its final distance (m)."""
    tr = run.trajectories
    T, n = tr.cost.shape[1], len(rows)
    zeros = np.zeros(n, dtype=np.int64)
    return {
        "episode_index": np.arange(n),
        "tasks": [[tasks[i]] for i in task],
        "length": np.full(n, T),
        "data/chunk_index": zeros,
        "data/file_index": zeros,
        "dataset_from_index": np.arange(n) * T,
        "dataset_to_index": (np.arange(n) + 1) * T,
        "meta/episodes/chunk_index": zeros,
        "meta/episodes/file_index": zeros,
        "condition": tr.condition.numpy()[rows],
        "final_distance": tr.final_distance.numpy()[rows],
    }


def _video(
    root: Path, run: RunData, rows: np.ndarray, fps: int, film: Film
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The camera stream of the episodes ``rows``, filmed into one video; returns its
    feature and its columns of the episodes' table (where each episode's frames are)."""
    path = root / VIDEO_PATH.format(video_key=CAMERA, chunk_index=0, file_index=0)
    path.parent.mkdir(parents=True)
    width, height = film(run, rows.tolist(), path, fps)
    feature = {
        "dtype": "video",
        "shape": [height, width, 3],
        "names": ["height", "width", "channels"],
        "info": {
            "video.height": height,
            "video.width": width,
            "video.codec": "h264",
            "video.pix_fmt": "yuv420p",
            "video.is_depth_map": False,
            "video.fps": fps,
            "video.channels": 3,
            "has_audio": False,
        },
    }
    T, n = run.trajectories.cost.shape[1], len(rows)
    start = np.arange(n) * T / fps
    zeros = np.zeros(n, dtype=np.int64)
    columns = {"chunk_index": zeros, "file_index": zeros, "from_timestamp": start,
               "to_timestamp": start + T / fps}  # fmt: skip
    return feature, {f"videos/{CAMERA}/{name}": v for name, v in columns.items()}


def _write_lerobot(root: Path, run: RunData, rows: np.ndarray, fps: int, film: Film | None) -> None:
    """The dataset's files under the empty folder ``root``."""
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    tasks, task = _episode_tasks(run, rows)
    columns = _columns(run, rows, fps, task)
    frames = {
        key: pa.FixedSizeListArray.from_arrays(pa.array(v.reshape(-1)), v.shape[1])
        if v.ndim == 2
        else pa.array(v)
        for key, v in columns.items()
    }
    for folder in ("data/chunk-000", "meta/episodes/chunk-000"):
        (root / folder).mkdir(parents=True)
    pq.write_table(pa.table(frames), root / DATA_PATH.format(chunk_index=0, file_index=0))
    pd.DataFrame({"task_index": range(len(tasks))}, index=tasks).to_parquet(
        root / "meta" / "tasks.parquet"
    )
    features, episodes = _features(run, columns), _episodes(run, rows, tasks, task)
    if film is not None:
        features[CAMERA], placed = _video(root, run, rows, fps, film)
        episodes |= placed
    pq.write_table(pa.table(episodes), root / "meta" / "episodes" / f"{CHUNK_FILE}.parquet")
    info = {
        "codebase_version": VERSION,
        "robot_type": Path(run.meta["arm"]["source_urdf_path"]).stem,
        "total_episodes": len(rows),
        "total_frames": len(columns["index"]),
        "total_tasks": len(tasks),
        "chunks_size": 1000,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200,
        "fps": fps,
        "splits": {"train": f"0:{len(rows)}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if film is not None else None,
        "features": features,
    }
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    stats = {key: _stats(v) for key, v in columns.items()}
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))


def export_lerobot(
    run_dir: str | Path, out_dir: str | Path, force: bool = False, film: Film | None = None
) -> ExportReport:
    """Write the run's successful trajectories as a LeRobot dataset (format v3.0) in the
    folder ``out_dir`` (module docstring); ``LeRobotDataset(repo_id, root=out_dir)`` reads it.

    :param run_dir: a run folder made by ``scripts/run_stream.py``.
    :param out_dir: the dataset folder to create.
    :param force: replace an existing ``out_dir``.
    :param film: films the episodes' camera stream (:data:`Film`); None: no video.
    :returns: what was written (trajectories: the episodes; steps: their frames).
    """
    start = time.perf_counter()
    out = Path(out_dir)
    try:
        import pandas  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError:
        raise LolgpsError(f"the LeRobot export needs pyarrow and pandas: {INSTALL}") from None
    check_output(out, force)
    run = read_run(run_dir)
    fps = frames_per_second(run.task.world.dt)
    rows = np.flatnonzero(run.trajectories.success.numpy())
    if len(rows) == 0:
        raise LolgpsError(f"run {run_dir} holds no successful trajectory to export")
    staging = out.with_name(f".{out.name}.partial")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        _write_lerobot(staging, run, rows, fps, film)
        fsync_tree(staging)
        move_into_place(staging, out)
    except (OSError, ValueError) as error:
        raise LolgpsError(f"cannot write LeRobot dataset {out}: {one_line(error)}") from error
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    T = run.trajectories.cost.shape[1]
    return ExportReport(out, len(rows), len(rows) * T, tree_size(out), time.perf_counter() - start)
