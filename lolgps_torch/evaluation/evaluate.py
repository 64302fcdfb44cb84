"""The Fig. 4 evaluation of a run folder (ALGORITHM.md section 9).

For each training stage, the global policy checkpointed after the stage's last condition runs
without noise (its mean action ``u_t = mu_theta(x_t)``) at every test position; per position
it keeps the final tip distance, the total cost ``sum_t l(x_t, u_t)`` and success. Positions are
grouped (test areas, or one group per explicit position) and summarised per (stage, group)
with :mod:`lolgps_torch.evaluation.metrics`; forgetting, average success and forward transfer
follow.

Rollouts are cut into fixed batches of ``batch_size`` positions, stage by stage, and the
batches are shared between this process and spawned workers. Each batch always holds the same
positions and a rollout does not depend on what its world ran before, so the results do not
depend on the number of workers. Only plain data crosses processes: this process builds the
:class:`PegTask` and scores every rollout; a worker (:mod:`lolgps_torch.evaluation.worker`)
receives the task's arm, world settings and placement, builds its own worlds (a PyBullet client
cannot be pickled), loads the checkpoints and returns states, actions and final distances.
"""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing
import multiprocessing.queues
import os
import queue
import sys
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any, NamedTuple

import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, area_centres, area_of, sample_area_positions
from lolgps_torch.evaluation.metrics import (
    aggregate,
    average_final_success,
    first_training_stage,
    forgetting,
    forward_transfer,
    mean_defined,
)
from lolgps_torch.evaluation.worker import (
    Failure,
    Job,
    PolicyRoller,
    Position,
    Rollouts,
    RolloutSetup,
    next_job,
    run_worker,
)
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.task import PegTask, task_config_from_dict

CONFIG_FILE = "config.json"
SUMMARY_FILE = "summary.json"
EVAL_FILE = "eval.json"
CHECKPOINT_DIR = "checkpoints"


@dataclass(frozen=True)
class RunInfo:
    """What the evaluation reads from a run's ``config.json``."""

    task: dict[str, Any]  # dataclasses.asdict(TaskConfig)
    conditions: list[Position]
    stages: list[dict[str, Any]]
    method: str
    seed: int


class JobResult(NamedTuple):
    """Per position of a :class:`Job`: final tip distance (m), total cost, success."""

    final_distance: list[float]
    total_cost: list[float]
    success: list[bool]


def checkpoint_dir(run_dir: str | Path, condition: int) -> Path:
    """The folder of the global policy saved after ``condition``."""
    return Path(run_dir) / CHECKPOINT_DIR / f"after_condition_{condition:03d}"


def read_run(run_dir: str | Path) -> RunInfo:
    """Read and check ``run_dir/config.json``; raise :class:`LolgpsError` if it is missing or
    malformed."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise LolgpsError(f"run folder not found: {run_dir}")
    path = run_dir / CONFIG_FILE
    try:
        config = json.loads(path.read_text())
        task = config["task"]
        task_config_from_dict(task)
        conditions = [(float(dx), float(dy)) for dx, dy in config["conditions"]]
        stages: list[dict[str, Any]] = [
            {"name": str(s["name"]), "last_condition": int(s["last_condition"])}
            for s in config["stages"]
        ]
        info = RunInfo(task, conditions, stages, str(config["method"]), int(config["seed"]))
    except OSError as error:
        raise LolgpsError(f"cannot read {path}: {error.strerror or error}") from None
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        raise LolgpsError(f"corrupt {path}: {type(error).__name__}: {error}") from None
    lasts = [int(s["last_condition"]) for s in stages]
    if not stages or lasts != sorted(set(lasts)) or not 0 <= lasts[-1] < len(conditions):
        raise LolgpsError(
            f"corrupt {path}: stages must end at increasing conditions below {len(conditions)}, "
            f"got last_condition {lasts}"
        )
    return info


def stage_checkpoints(run_dir: str | Path, info: RunInfo) -> list[tuple[int, Path]]:
    """``(stage index, checkpoint folder)`` of the stages to evaluate, each checked loadable.

    Batch GPS checkpoints only its final policy, so its earlier stages are skipped; any other
    missing checkpoint is an error."""
    found = []
    for s, stage in enumerate(info.stages):
        folder = checkpoint_dir(run_dir, stage["last_condition"])
        if not folder.is_dir():
            if info.method == "batch" and s < len(info.stages) - 1:
                continue
            raise LolgpsError(f"missing checkpoint for stage {stage['name']}: {folder}")
        GaussianPolicy.load(folder)
        found.append((s, folder))
    return found


def _score(task: PegTask, job: Job, rollouts: Rollouts) -> JobResult:
    """Per position of ``job``: final tip distance, total cost ``sum_t l(x_t, u_t)`` and
    success, by :meth:`PegTask.score`."""
    x, u, final = (torch.from_numpy(a) for a in rollouts)
    with torch.no_grad():
        scored = task.score(x, u, final, job.positions)
    return JobResult(
        scored.final_distance.tolist(), scored.cost.sum(dim=1).tolist(), scored.success.tolist()
    )


def _unpack(item: tuple[int, Rollouts | Failure]) -> tuple[int, Rollouts]:
    """A worker's ``(job index, rollouts)``; its failure raised here (a user error as one
    :class:`LolgpsError` line, a bug as a :class:`RuntimeError` with its traceback)."""
    index, result = item
    if isinstance(result, Failure):
        if result.user_error:
            raise LolgpsError(result.message)
        raise RuntimeError(f"an evaluation worker failed:\n{result.message}")
    return index, result


def _ready(
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]],
) -> Iterator[tuple[int, Rollouts]]:
    """The workers' results already queued, without waiting for more."""
    while True:
        try:
            item = results.get_nowait()
        except queue.Empty:
            return
        yield _unpack(item)


def _collect(
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]],
    missing: set[int],
    processes: Sequence[BaseProcess],
) -> Iterator[tuple[int, Rollouts]]:
    """The workers' results for the job indices ``missing``, as they arrive; raises
    :class:`LolgpsError` if every worker has died with some still missing."""
    while missing:
        try:
            item = results.get(timeout=0.5)
        except queue.Empty:
            if not any(p.is_alive() for p in processes) and results.empty():
                codes = [p.exitcode for p in processes]
                raise LolgpsError(f"evaluation workers died (exit codes {codes})") from None
            continue
        index, rollouts = _unpack(item)
        missing.discard(index)
        yield index, rollouts


@contextlib.contextmanager
def _main_script_hidden() -> Iterator[None]:
    """Hide the ``__main__`` module's file and spec while workers are spawned, so they do not
    re-run the main script. multiprocessing re-runs it in each spawned process, for pickled
    references into it; the workers need none (their target and data come from this package),
    and a script that imports this module would cost each worker pytorch_kinematics and
    yourdfpy's start-up, about a second."""
    main = sys.modules["__main__"]
    spec, path = main.__spec__, main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        yield
    finally:
        main.__spec__ = spec
        if path is not None:
            main.__file__ = path


def run_jobs(
    task: dict[str, Any], jobs: Sequence[Job], workers: int, n_worlds: int
) -> list[JobResult]:
    """Results of ``jobs``, in order, from ``workers`` processes: this one and ``workers - 1``
    spawned ones, all on one torch thread, each claiming the next unclaimed job.

    This process starts the workers, builds the task from ``task`` (``dataclasses.asdict`` of
    a :class:`TaskConfig`) with ``n_worlds`` worlds, sends the workers its arm, world settings
    and placement (:class:`RolloutSetup`), then rolls out jobs itself at once. The workers only
    build worlds and run policies (start-up: 2-3 CPU-seconds, mostly importing torch; the
    task's inverse kinematics and cost are not theirs) and send back states, actions and final
    distances. This process scores every rollout with the task's cost as :meth:`PegTask.sample`
    does (the workers' as they arrive, between its own jobs), so the results do not depend on
    ``workers``."""
    if workers < 1:
        raise LolgpsError(f"need at least one worker, got {workers}")
    context = multiprocessing.get_context("spawn")
    counter = context.Value("q", 0)
    setups: multiprocessing.queues.Queue[RolloutSetup] = context.Queue()
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]] = context.Queue()
    processes = [
        context.Process(target=run_worker, args=(setups, list(jobs), counter, results))
        for _ in range(min(workers, len(jobs)) - 1)
    ]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    peg = None
    try:
        with _main_script_hidden():
            for process in processes:
                process.start()  # the workers import while this process builds the task
        peg = PegTask(task_config_from_dict(task), n_worlds=n_worlds)
        setup = RolloutSetup(
            peg.arm, peg.config.world, peg.geometry.nominal_mouth, peg.geometry.q0, n_worlds
        )
        for _ in processes:
            setups.put(setup)
        roller = PolicyRoller(peg.sampler, peg.layout)
        found: dict[int, JobResult] = {}
        while (index := next_job(counter, len(jobs))) is not None:
            found[index] = _score(peg, jobs[index], roller(jobs[index]))
            for i, rollouts in _ready(results):
                found[i] = _score(peg, jobs[i], rollouts)
        for i, rollouts in _collect(results, set(range(len(jobs))) - set(found), processes):
            found[i] = _score(peg, jobs[i], rollouts)
        return [found[i] for i in range(len(jobs))]
    finally:
        for process in processes:
            process.terminate()  # those still starting up when every job was taken
            process.join()
        if peg is not None:
            peg.close()
        torch.set_num_threads(threads)


def _area_groups(areas: AreaConfig) -> list[dict[str, Any]]:
    """One group per test area: its centre, radius and sampled positions."""
    centres = area_centres(areas)
    sampled = sample_area_positions(areas)
    return [
        {
            "label": f"area {k}",
            "centre": centres[k].tolist(),
            "centre_distance": float(centres[k].norm()),
            "radius": areas.radius,
            "positions": sampled[k].tolist(),
        }
        for k in range(areas.n_areas)
    ]


def _position_groups(positions: Sequence[Position]) -> list[dict[str, Any]]:
    """One group per explicit position, its "centre" the position itself."""
    if not positions:
        raise LolgpsError("no test positions given")
    return [
        {
            "label": f"({dx:+.3f}, {dy:+.3f})",
            "centre": [dx, dy],
            "centre_distance": math.hypot(dx, dy),
            "radius": None,
            "positions": [[dx, dy]],
        }
        for dx, dy in positions
    ]


def _iterations_to_success(summary_path: Path) -> dict[tuple[float, float], int | None]:
    """Iterations up to and including the first successful one (``first_success_iteration``
    is 0-based), keyed by the rounded hole offset."""
    try:
        entries = json.loads(summary_path.read_text())["conditions"]
        table: dict[tuple[float, float], int | None] = {}
        for entry in entries:
            key = (round(float(entry["offset"][0]), 9), round(float(entry["offset"][1]), 9))
            first = entry["first_success_iteration"]
            table[key] = None if first is None else int(first) + 1
    except OSError as error:
        raise LolgpsError(f"cannot read {summary_path}: {error.strerror or error}") from None
    except (ValueError, KeyError, TypeError, IndexError) as error:
        raise LolgpsError(f"corrupt {summary_path}: {type(error).__name__}: {error}") from None
    return table


def _transfer(
    run_dir: Path, info: RunInfo, scratch: str | Path | None
) -> list[dict[str, Any]] | None:
    """Forward transfer per condition against the ``scratch`` run (None without a summary)."""
    if not (run_dir / SUMMARY_FILE).exists():
        return None
    keys = [(round(dx, 9), round(dy, 9)) for dx, dy in info.conditions]
    ours = _iterations_to_success(run_dir / SUMMARY_FILE)
    theirs = _iterations_to_success(Path(scratch) / SUMMARY_FILE) if scratch is not None else {}
    rows = forward_transfer([ours.get(k) for k in keys], [theirs.get(k) for k in keys])
    return [
        {"condition": c, "offset": list(info.conditions[c]), **row} for c, row in enumerate(rows)
    ]


def _metrics(
    stages: list[dict[str, Any]],
    evaluated: list[int],
    info: RunInfo,
    areas: AreaConfig | None,
    transfer: list[dict[str, Any]] | None,
) -> dict[str, Any]:
    """Forgetting per area (None in positions mode), average success, forward transfer."""
    rates = [[g["success_rate"]["mean"] for g in s["groups"]] for s in stages]
    metrics: dict[str, Any] = {
        "average_success": [average_final_success(r) for r in rates],
        "average_final_success": average_final_success(rates[-1]),
        "forward_transfer": transfer,
        "mean_transfer_ratio": mean_defined([r["ratio"] for r in transfer]) if transfer else None,
        "trained_by_stage": None,
        "forgetting": None,
    }
    if areas is None:
        return metrics
    condition_areas = area_of(torch.tensor(info.conditions), areas).tolist()
    trained = first_training_stage(condition_areas, info.stages, areas.n_areas)
    position = {s: i for i, s in enumerate(evaluated)}
    trained_eval = [None if s is None else position.get(s) for s in trained]
    metrics["trained_by_stage"] = [None if s is None else info.stages[s]["name"] for s in trained]
    per_metric = {}
    for name, higher_is_better in (
        ("final_distance", False),
        ("total_cost", False),
        ("success_rate", True),
    ):
        values = [[g[name]["mean"] for g in s["groups"]] for s in stages]
        per_area = forgetting(values, trained_eval, higher_is_better)
        per_metric[name] = {"per_area": per_area, "mean": mean_defined(per_area)}
    metrics["forgetting"] = per_metric
    return metrics


def evaluate_run(
    run_dir: str | Path,
    workers: int = 1,
    areas: AreaConfig | None = None,
    positions: Sequence[Position] | None = None,
    scratch: str | Path | None = None,
    batch_size: int = 10,
) -> dict[str, Any]:
    """Evaluate every stage's checkpoint of ``run_dir`` and write ``run_dir/eval.json``.

    :param workers: processes to spread the rollouts over (results do not depend on it).
    :param areas: test areas (default :class:`AreaConfig`); exclusive with ``positions``.
    :param positions: explicit hole offsets ``(dx, dy)`` (m), each its own group.
    :param scratch: a run folder whose ``summary.json`` gives from-scratch iterations to first
        success, for forward transfer.
    :param batch_size: rollouts per batch (worlds per worker).
    :returns: the dict written to ``eval.json``.
    """
    if areas is not None and positions is not None:
        raise LolgpsError("evaluate either test areas or explicit positions, not both")
    if batch_size < 1:
        raise LolgpsError(f"batch size must be positive, got {batch_size}")
    if positions is None and areas is None:
        areas = AreaConfig()
    run_dir = Path(run_dir)
    info = read_run(run_dir)
    checkpoints = stage_checkpoints(run_dir, info)
    groups = _area_groups(areas) if areas is not None else _position_groups(positions or [])
    flat: list[Position] = [(p[0], p[1]) for g in groups for p in g["positions"]]
    batches = [tuple(flat[i : i + batch_size]) for i in range(0, len(flat), batch_size)]
    jobs = [Job(str(folder), batch) for _, folder in checkpoints for batch in batches]
    results = run_jobs(info.task, jobs, workers, min(batch_size, len(flat)))

    stages = []
    for i, (s, folder) in enumerate(checkpoints):
        mine = results[i * len(batches) : (i + 1) * len(batches)]
        per_position = {
            field: _split([v for r in mine for v in getattr(r, field)], groups)
            for field in JobResult._fields
        }
        stages.append(
            {
                **info.stages[s],
                "checkpoint": str(folder.relative_to(run_dir)),
                "groups": aggregate(
                    per_position["final_distance"],
                    per_position["total_cost"],
                    per_position["success"],
                ),
                "per_position": per_position,
            }
        )
    evaluation = {
        "method": info.method,
        "seed": info.seed,
        "mode": "positions" if positions is not None else "areas",
        "area_config": asdict(areas) if areas is not None else None,
        "success_threshold": task_config_from_dict(info.task).world.success_threshold,
        "training": {"conditions": [list(c) for c in info.conditions], "stages": info.stages},
        "groups": groups,
        "stages": stages,
        "metrics": _metrics(
            stages, [s for s, _ in checkpoints], info, areas, _transfer(run_dir, info, scratch)
        ),
    }
    write_json_atomic(run_dir / EVAL_FILE, evaluation)
    return evaluation


def _split(values: list[Any], groups: list[dict[str, Any]]) -> list[list[Any]]:
    """Cut a flat per-position list into the groups' sizes."""
    out, start = [], 0
    for g in groups:
        out.append(values[start : start + len(g["positions"])])
        start += len(g["positions"])
    return out


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write ``data`` as JSON through a temporary sibling and ``os.replace``, so a reader never
    sees a partial file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    try:
        with open(tmp, "w") as fh:
            json.dump(data, fh, indent=1)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def format_table(evaluation: dict[str, Any]) -> str:
    """A plain-text table: per stage and group, distance, cost and success with 95% CIs."""

    def interval(stat: dict[str, float | None], fmt: str) -> str:
        if stat["low"] is None or stat["high"] is None:
            return f"{stat['mean']:{fmt}}"
        return f"{stat['mean']:{fmt}} [{stat['low']:{fmt}}, {stat['high']:{fmt}}]"

    lines = [
        f"{'stage':<8} {'group':<18} {'centre (m)':>10}  {'final distance (m)':<26} "
        f"{'total cost':<28} success"
    ]
    for stage in evaluation["stages"]:
        for group, stats in zip(evaluation["groups"], stage["groups"], strict=True):
            lines.append(
                f"{stage['name']:<8} {group['label']:<18} {group['centre_distance']:>10.3f}  "
                f"{interval(stats['final_distance'], '.4f'):<26} "
                f"{interval(stats['total_cost'], '.1f'):<28} "
                f"{interval(stats['success_rate'], '.2f')}"
            )
    metrics = evaluation["metrics"]
    lines.append(f"average final success: {metrics['average_final_success']:.3f}")
    if metrics["forgetting"] is not None:
        for name, forgot in metrics["forgetting"].items():
            cells = ["  -  " if v is None else f"{v:+.3g}" for v in forgot["per_area"]]
            lines.append(f"forgetting of {name} per area (positive: worse): {' '.join(cells)}")
    if metrics["forward_transfer"] is not None:
        cells = [
            f"c{row['condition']}: {row['iterations']}/{row['scratch_iterations']}"
            for row in metrics["forward_transfer"]
        ]
        lines.append("iterations to first success (run/scratch): " + ", ".join(cells))
    return "\n".join(lines)
