"""The Fig. 4 evaluation of a run folder (docs/ALGORITHM.md section 9).

For each training stage, the global policy checkpointed after the stage's last condition runs
without noise (its mean action ``u_t = mu_theta(x_t)``) at every test position; per position
it keeps the final tip distance, the total cost ``sum_t l(x_t, u_t)`` and success. Positions are
grouped (test areas, or one group per explicit position) and summarised per (stage, group)
with :mod:`lolgps_torch.evaluation.metrics`; forgetting, average success and forward transfer
follow. The rollouts run in batches over processes (:mod:`lolgps_torch.evaluation.jobs`); the
task is built from the run folder's own URDF copy, so a copied run folder evaluates alike.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import torch

from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.run_folder import RunFolder, read_json, write_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, area_centres, area_of, sample_area_positions
from lolgps_torch.evaluation.jobs import JobResult, run_jobs, run_jobs_on_ray
from lolgps_torch.evaluation.metrics import (
    aggregate,
    average_final_success,
    first_training_stage,
    forgetting,
    mean_defined,
)
from lolgps_torch.evaluation.square import SquareConfig, square_test_positions
from lolgps_torch.evaluation.transfer import compute_scratch, rates_by_condition, transfer_rows
from lolgps_torch.evaluation.worker import Job, PolicyState, Position
from lolgps_torch.lolgps.run import RunInfo, read_run
from lolgps_torch.sim.franka import SIMULATED, RealArmConfig
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.simulator import Simulator


def stage_policies(folder: RunFolder, info: RunInfo) -> list[tuple[int, PolicyState]]:
    """``(stage index, policy)`` of the stages to evaluate, each loaded from its checkpoint.

    Batch GPS checkpoints only its final policy, so its earlier stages are skipped; any other
    missing checkpoint is an error."""
    found = []
    for s, stage in enumerate(info.stages):
        checkpoint = folder.checkpoint_dir(stage["last_condition"])
        if not checkpoint.is_dir():
            if info.method == "batch" and s < len(info.stages) - 1:
                continue
            raise LolgpsError(f"missing checkpoint for stage {stage['name']}: {checkpoint}")
        name = str(checkpoint.relative_to(folder.path))
        found.append((s, PolicyState.of(name, load_policy(checkpoint))))
    return found


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


def _square_group(square: SquareConfig, area_seed: int, info: RunInfo) -> list[dict[str, Any]]:
    """One group: the square's held-out test positions (never a training one)."""
    positions = square_test_positions(square, area_seed, info.conditions)
    return [
        {
            "label": f"square {square.side:g} m",
            "centre": [0.0, 0.0],
            "centre_distance": 0.0,
            "radius": square.side / 2,
            "positions": [list(p) for p in positions],
        }
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


def _scratch_from(run: RunFolder, info: RunInfo) -> list[list[float]]:
    """Per condition of ``info``, the success rates of the condition at the same offset in
    another run (e.g. a naive one)."""
    other = read_run(run)
    rates = rates_by_condition(run.read_metrics())
    keys = {(round(dx, 9), round(dy, 9)): c for c, (dx, dy) in enumerate(other.conditions)}
    out = []
    for dx, dy in info.conditions:
        c = keys.get((round(dx, 9), round(dy, 9)))
        if c is None or not rates.get(c):
            raise LolgpsError(f"{run.path} has no condition at ({dx:+.3f}, {dy:+.3f})")
        out.append(rates[c])
    return out


def _transfer(
    folder: RunFolder, info: RunInfo, scratch: str | Path | None, workers: int
) -> list[dict[str, Any]] | None:
    """Forward transfer per condition (None before the run finished): against from-scratch
    learners run here (``scratch="auto"``), another run's conditions, or nothing."""
    if not folder.summary_path.exists():
        return None
    if scratch == "auto":
        rates: list[list[float]] | None = compute_scratch(folder, info, workers)
    else:
        rates = _scratch_from(RunFolder(scratch), info) if scratch is not None else None
    entries = folder.read_summary()["conditions"]
    return transfer_rows(info, folder.read_metrics(), entries, rates)


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
        "mean_forward_transfer": (
            mean_defined([r["forward_transfer"] for r in transfer[1:]]) if transfer else None
        ),
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


def _stage_results(
    folder: RunFolder,
    info: RunInfo,
    policies: list[tuple[int, PolicyState]],
    groups: list[dict[str, Any]],
    results: list[JobResult],
) -> list[dict[str, Any]]:
    """Per evaluated stage: its name, checkpoint, per-group statistics and per-position
    results (``results`` holds each stage's batches in turn)."""
    per_stage = len(results) // len(policies)
    stages = []
    for i, (s, policy) in enumerate(policies):
        mine = results[i * per_stage : (i + 1) * per_stage]
        per_position = {
            field: _split([v for r in mine for v in getattr(r, field)], groups)
            for field in JobResult._fields
        }
        stats = aggregate(
            per_position["final_distance"], per_position["total_cost"], per_position["success"]
        )
        for group, faults, speeds in zip(
            stats, per_position["fault"], per_position["peak_speed"], strict=True
        ):
            group["faults"], group["peak_speed"] = sum(faults), max(speeds, default=0.0)
        stages.append(
            {
                **info.stages[s],
                "checkpoint": policy.name,
                "groups": stats,
                "faults": sum(g["faults"] for g in stats),
                "peak_speed": max(g["peak_speed"] for g in stats),
                "per_position": per_position,
            }
        )
    return stages


def _roll_out(
    info: RunInfo,
    states: list[PolicyState],
    groups: list[dict[str, Any]],
    workers: int,
    batch_size: int,
    ray: str | None,
    real: RealArmConfig,
) -> list[JobResult]:
    """Every policy of ``states`` at every position of ``groups``, in batches of
    ``batch_size`` rollouts, on ``workers`` processes or (``ray``) on Ray actors."""
    flat: list[Position] = [(p[0], p[1]) for g in groups for p in g["positions"]]
    batches = [tuple(flat[i : i + batch_size]) for i in range(0, len(flat), batch_size)]
    jobs = [Job(i, batch) for i in range(len(states)) for batch in batches]
    n_worlds = min(batch_size, len(flat))
    if ray is None:
        return run_jobs(info.task, states, jobs, workers, n_worlds, real)
    address = None if ray == "local" else ray
    return run_jobs_on_ray(info.task, states, jobs, address, workers, n_worlds)


def evaluate_run(
    run_dir: str | Path,
    workers: int = 1,
    areas: AreaConfig | None = None,
    positions: Sequence[Position] | None = None,
    scratch: str | Path | None = None,
    batch_size: int = 10,
    square: tuple[SquareConfig, int] | None = None,
    ray: str | None = None,
    plant: PlantConfig | None = None,
    sim: Simulator | None = None,
    real: RealArmConfig = SIMULATED,
) -> dict[str, Any]:
    """Evaluate every stage's checkpoint of ``run_dir`` and write its ``eval.json``.

    :param workers: processes to spread the rollouts over (results do not depend on it).
    :param areas: test areas (default :class:`AreaConfig`), scaled by the run's geometry scale
        (``TaskConfig.scale``) as its hole offsets were; exclusive with ``positions``.
    :param positions: explicit hole offsets ``(dx, dy)`` (m), each its own group.
    :param scratch: the from-scratch baselines for forward transfer: ``"auto"`` learns every
        condition alone here (cached in the run's ``scratch.json``), or a run folder whose
        conditions at the same offsets serve (e.g. a naive run).
    :param batch_size: rollouts per batch (worlds per worker).
    :param square: the 2-D stream's test set instead of areas or positions: its geometry
        (its side scaled as ``areas`` are) and the seed of its positions.
    :param ray: run the rollouts on Ray instead of processes: ``"local"`` starts a local
        instance of ``workers`` CPUs, anything else is a cluster address (e.g. ``auto``).
    :param plant: the simulated arm to evaluate on (default: the run's own).
    :param sim: the simulator to evaluate in (default: the run's own).
    :param real: the arm to evaluate on: a real one (``--arm franka``) runs the rollouts one
        at a time in this process.
    :returns: the dict written to ``eval.json``.
    """
    if areas is not None and positions is not None:
        raise LolgpsError("evaluate either test areas or explicit positions, not both")
    if batch_size < 1:
        raise LolgpsError(f"batch size must be positive, got {batch_size}")
    if positions is None and areas is None and square is None:
        areas = AreaConfig()
    folder = RunFolder(run_dir)
    info = read_run(folder)
    factor = info.task.scale
    areas = (
        replace(areas, spacing=areas.spacing * factor, radius=areas.radius * factor)
        if areas
        else None
    )
    square = (replace(square[0], side=square[0].side * factor), square[1]) if square else None
    task = replace(info.task, plant=plant or info.task.plant, sim=sim or info.task.sim)
    info = replace(info, task=task)
    policies = stage_policies(folder, info)
    if square is not None:
        groups = _square_group(*square, info)
    else:
        groups = _area_groups(areas) if areas is not None else _position_groups(positions or [])
    rolled = [policy for _, policy in policies]
    results = _roll_out(info, rolled, groups, workers, batch_size, ray, real)
    stages = _stage_results(folder, info, policies, groups, results)
    evaluated = [s for s, _ in policies]
    evaluation = {
        "method": info.method,
        "seed": info.seed,
        "mode": "square" if square else "positions" if positions is not None else "areas",
        "area_config": asdict(areas) if areas is not None else None,
        "success_threshold": info.task.world.success_threshold,
        "plant": asdict(info.task.plant),
        "sim": info.task.sim,
        "training": {"conditions": [list(c) for c in info.conditions], "stages": info.stages},
        "groups": groups,
        "stages": stages,
        "arm_rollouts": {"evaluation": sum(len(r.success) for r in results)},
        "metrics": _metrics(
            stages, evaluated, info, areas, _transfer(folder, info, scratch, workers)
        ),
    }
    write_json(folder.eval_path, evaluation)
    return evaluation


def read_evaluation(run_dir: str | Path) -> dict[str, Any]:
    """A run's ``eval.json`` as :func:`evaluate_run` wrote it."""
    evaluation = read_json(RunFolder(run_dir).eval_path)
    if not isinstance(evaluation, dict):
        raise LolgpsError(f"corrupt {RunFolder(run_dir).eval_path}: not a JSON object")
    return evaluation


def _split(values: list[Any], groups: list[dict[str, Any]]) -> list[list[Any]]:
    """Cut a flat per-position list into the groups' sizes."""
    out, start = [], 0
    for g in groups:
        out.append(values[start : start + len(g["positions"])])
        start += len(g["positions"])
    return out
