"""Forward transfer as Continual World defines it, from the per-iteration success rates.

    AUC_i = mean sample success rate over condition i's first ``horizon`` iterations
    FT_i  = (AUC_i - AUC_scratch,i) / (1 - AUC_scratch,i)

with AUC_scratch,i that of the same condition learnt alone from the hold controller with the
same seed. A condition whose learning stopped before ``horizon`` iterations keeps its last
success rate for the rest (its learning is done, not failed).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from lolgps_torch.errors import LolgpsError

HORIZON = 10


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
