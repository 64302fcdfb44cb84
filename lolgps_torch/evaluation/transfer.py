"""Forward transfer as Continual World defines it, from the per-iteration success rates.

    AUC_i = mean sample success rate over condition i's first ``horizon`` iterations
    FT_i  = (AUC_i - AUC_scratch,i) / (1 - AUC_scratch,i)

with AUC_scratch,i that of the same condition learnt alone from the hold controller with the
same seed. A condition whose learning stopped before ``horizon`` iterations keeps its last
success rate for the rest (its learning is done, not failed).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import torch

from lolgps_torch.data.run_folder import RunFolder, read_json, write_json
from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
from lolgps_torch.lolgps.run import RunInfo
from lolgps_torch.progress import progress
from lolgps_torch.task import PegTask, TaskConfig

HORIZON = 10
SCRATCH_FILE = "scratch.json"
Position = tuple[float, float]


def success_auc(rates: Sequence[float], horizon: int = HORIZON) -> float:
    """Mean of ``rates`` (per iteration, in order) over the first ``horizon`` iterations, the
    last rate standing in for iterations that were not run."""
    if not rates:
        raise LolgpsError("no iterations to compute a success AUC from")
    padded = list(rates[:horizon]) + [rates[-1]] * max(0, horizon - len(rates))
    return sum(padded) / horizon


def forward_transfer(auc: float, auc_scratch: float) -> float | None:
    """``(auc - auc_scratch) / (1 - auc_scratch)``; None where the scratch learner succeeds on
    every sample from the start (nothing left to transfer)."""
    if auc_scratch >= 1.0:
        return None
    return (auc - auc_scratch) / (1.0 - auc_scratch)


def rates_by_condition(records: Iterable[Mapping[str, Any]]) -> dict[int, list[float]]:
    """Per condition, the success rate of each iteration, from ``metrics.jsonl`` records."""
    rates: dict[int, list[float]] = {}
    for record in records:
        if "iteration" in record and "success_rate" in record:
            rates.setdefault(int(record["condition"]), []).append(float(record["success_rate"]))
    return rates


def scratch_rates(
    task: TaskConfig, offset: Position, seed: int, local: LocalConfig, iterations: int
) -> list[float]:
    """The sample success rate of each of the first ``iterations`` iterations of the
    condition at ``offset`` learnt alone from the hold controller, with the learner's seed
    ``seed`` (what ``scripts/train_condition.py --seed seed`` runs). A numerical failure
    ends the list early."""
    peg = PegTask(task, n_worlds=local.samples)
    rates: list[float] = []
    try:
        learner = LocalLearner(peg, offset, local, seed=seed)
        for i in range(iterations):
            samples, _, _ = iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
            rates.append(float(samples.success.double().mean()))
    except NumericalError:
        pass
    finally:
        peg.close()
    return rates or [0.0]


def _scratch_job(job: tuple[TaskConfig, Position, int, LocalConfig, int]) -> list[float]:
    torch.set_num_threads(1)
    return scratch_rates(*job)


def compute_scratch(
    folder: RunFolder, info: RunInfo, workers: int, horizon: int = HORIZON
) -> list[list[float]]:
    """Per condition of the run, the from-scratch success rates (:func:`scratch_rates` with
    the condition's seed in the stream), in ``workers`` processes; kept in the run folder's
    ``scratch.json`` and reused while it matches the run's conditions and horizon."""
    seeds = [info.seed * 1000 + c for c in range(len(info.conditions))]
    wanted = {"horizon": horizon, "offsets": [list(o) for o in info.conditions], "seeds": seeds}
    path = folder.path / SCRATCH_FILE
    if path.exists():
        cached = read_json(path)
        if isinstance(cached, dict) and {k: cached.get(k) for k in wanted} == wanted:
            return [list(map(float, r)) for r in cached["rates"]]
    jobs = [
        (info.task, o, s, info.stream.local, horizon)
        for o, s in zip(info.conditions, seeds, strict=True)
    ]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=max(1, workers), mp_context=context) as pool:
        rates = list(progress(pool.map(_scratch_job, jobs), len(jobs), "scratch baselines"))
    write_json(path, {**wanted, "rates": rates})
    return rates


def transfer_rows(
    info: RunInfo,
    records: list[dict[str, Any]],
    entries: list[dict[str, Any]],
    scratch: list[list[float]] | None,
) -> list[dict[str, Any]]:
    """Per condition: rollouts, AUC of the run, AUC from scratch and FT (None without a
    scratch baseline)."""
    ours = rates_by_condition(records)
    rows = []
    for c, offset in enumerate(info.conditions):
        auc = success_auc(ours[c]) if ours.get(c) else None
        base = success_auc(scratch[c]) if scratch is not None else None
        ft = forward_transfer(auc, base) if auc is not None and base is not None else None
        rollouts = entries[c].get("rollouts") if c < len(entries) else None
        rows.append(
            {
                "condition": c,
                "offset": list(offset),
                "rollouts": rollouts,
                "auc": auc,
                "scratch_auc": base,
                "forward_transfer": ft,
            }
        )
    return rows
