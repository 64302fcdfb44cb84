"""Export a run folder as a Minari dataset whose environment spec rebuilds the task, so
``minari.load_dataset(name).recover_environment()`` is the environment the data came from.
The layout is documented in ``datasets/README.md``.

The dataset is written in a staging folder next to the output, fsynced and renamed into place,
so an interrupted export never leaves anything at the output path.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from lolgps_torch.data.dataset import (
    CONDITIONS,
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
from lolgps_torch.gym_env import ENV_ID
from lolgps_torch.progress import progress


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


def env_spec(run: RunData) -> gym.envs.registration.EnvSpec:
    """``lolgps_torch/PegInsertion-v0`` with the run's task (a plain dict, the URDF an absolute
    path) as its ``task_config`` keyword and the task's T as ``max_episode_steps``."""
    return dataclasses.replace(
        gym.spec(ENV_ID),
        kwargs={"task_config": asdict(run.task)},
        max_episode_steps=run.task.world.T,
    )


def _episodes(run: RunData) -> Iterator[Any]:
    """One Minari episode buffer per trajectory: T+1 observations, T steps."""
    from minari.data_collector import EpisodeBuffer

    tr = run.trajectories
    N, T = tr.cost.shape
    states, actions, rewards = tr.states.numpy(), tr.actions.numpy(), (-tr.cost).numpy()
    tip_distance = tip_distances(run)  # the env's info "tip_distance"
    success = tip_distance < run.meta["task"]["success_threshold"]
    truncations = np.arange(T) == T - 1
    for i in progress(range(N), N, "episodes"):
        yield EpisodeBuffer(
            id=i,
            options={"hole_offset": tr.hole_offset[i].tolist()},
            observations=states[i],
            actions=actions[i],
            rewards=rewards[i],
            terminations=np.zeros(T, dtype=bool),
            truncations=truncations,
            infos={"tip_distance": tip_distance[i], "success": success[i]},
        )


def _write_minari(name: str, run: RunData) -> None:
    """Create the Minari dataset ``name`` under the current ``MINARI_DATASETS_PATH``."""
    import minari

    env = gym.make(env_spec(run))
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=UserWarning, module=r"minari\.")
            dataset = minari.create_dataset_from_buffers(
                dataset_id=name,
                buffer=list(_episodes(run)),
                env=env,
                algorithm_name=f"lolgps_torch {run.root['method']}",
                description=(
                    "Successful peg-insertion trajectories of a lolgps_torch run: observations "
                    "are the states x_0..x_T, actions the torques u_0..u_{T-1}, rewards "
                    "-l(x_t, u_t); each episode's reset option hole_offset reproduces its start "
                    "in the recovered environment. See metadata['lolgps_torch'] and "
                    "datasets/README.md."
                ),
                data_format="hdf5",
            )
    finally:
        env.close()
    tr = run.trajectories
    dataset.storage.update_episode_metadata(
        {
            "condition": int(tr.condition[i]),
            "success": bool(tr.success[i]),
            "final_distance": float(tr.final_distance[i]),
            "total_cost": float(tr.total_cost[i]),
        }
        for i in range(tr.cost.shape[0])
    )
    conditions = {k: v.tolist() for k, v in run.conditions.items()}
    dataset.storage.update_metadata(
        {"lolgps_torch": {**run.root, **run.meta, CONDITIONS: conditions}}
    )


def export_minari(run_dir: str | Path, out_dir: str | Path, force: bool = False) -> ExportReport:
    """Write the run's trajectories as a Minari dataset (HDF5 storage) in folder ``out_dir``.

    The folder's name is the dataset id (``NAME-vVERSION``, no namespace) and its parent is the
    datasets root: load it with ``MINARI_DATASETS_PATH=<parent>`` and
    ``minari.load_dataset(<name>)``. One episode per trajectory: the T+1 states as
    observations, the T actions and rewards (``-cost``); the last step is a truncation. The
    environment spec rebuilds the run's task (:func:`env_spec`). Per-episode metadata
    (condition, success, final_distance, total_cost) and the reset option ``hole_offset`` are
    stored with each episode; the dataset metadata key ``lolgps_torch`` holds the schema's
    metadata.

    :param run_dir: a run folder made by ``scripts/run_stream.py``.
    :param out_dir: the dataset folder to create (``<datasets root>/<dataset id>``).
    :param force: replace an existing ``out_dir``.
    :returns: what was written (steps: the T transitions of every episode).
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
    check_output(out, force)
    run = read_run(run_dir)
    N, T = run.trajectories.cost.shape
    staging = out.with_name(f".{out.name}.partial")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        with _minari_root(staging):
            _write_minari(out.name, run)
        fsync_tree(staging / out.name)
        move_into_place(staging / out.name, out)
    except (OSError, ValueError) as error:
        raise LolgpsError(f"cannot write Minari dataset {out}: {one_line(error)}") from error
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return ExportReport(out, N, N * T, tree_size(out), time.perf_counter() - start)
