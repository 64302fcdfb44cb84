"""Retention: how well each training position is kept by the global policy after every S-step.

For a run with checkpoints after conditions ``0 .. K-1`` and D_g of every condition, two
``[K, K]`` tables, row ``k`` = the policy after condition ``k``'s S-step, column ``j`` =
condition ``j``:

- ``distance[k][j]``: the final distance (m) of the policy's noiseless rollout at position j;
  forgetting shows as a column that drops below the success threshold at ``k = j`` and rises
  above it later;
- ``fit[k][j]``: the policy's action error on condition j's stored states ``x`` in p_cur's
  standard deviations, ``mean_rows sqrt(d^T P_cur d)`` with ``d = mu_theta(x) - mu_cur(x)``
  (the S-step's own measure, eq. 8): it tells a policy that no longer fits its teacher on D_g
  from one that fits D_g but drifts off it in closed loop.

Entries for ``j > k`` (positions not yet learned) are measured too: they show what the policy
already does there before it is taught.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lolgps_torch.data.run_folder import atomic_write
from lolgps_torch.lolgps.run import LoadedRun
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.types import ConditionSamples


def fit_error(
    policy: GaussianPolicy, x: torch.Tensor, mean: torch.Tensor, prec: torch.Tensor
) -> torch.Tensor:
    """``sqrt(d^T P d)`` with ``d = mu_theta(x) - mean`` at states ``x: [..., dX]``, targets
    ``mean: [..., dU]`` and precisions ``prec: [..., dU, dU]`` -> ``[...]``."""
    with torch.no_grad():
        d = (policy(x) - mean).unsqueeze(-1)
    return (d.mT @ prec @ d).flatten(-3).clamp_min(0.0).sqrt()


def fit_by_window(policy: GaussianPolicy, loaded: LoadedRun, width: int = 10) -> list[float]:
    """The mean of :func:`fit_error` over every condition's D_g, per window of ``width`` time
    steps (``ceil(T / width)`` floats)."""
    errors = [
        fit_error(policy, r.samples.x, r.samples.mean_cur, r.samples.prec_cur)
        for r in loaded.records
        if r.samples.x.shape[0] > 0
    ]
    if not errors:
        return []
    return [float(w.mean()) for w in torch.cat(errors).mean(0).split(width)]


def retention(loaded: LoadedRun) -> dict[str, Any]:
    """The run's retention tables (module docstring) as JSON-able data."""
    offsets = [r.offset for r in loaded.records]
    task = loaded.make_task(n_worlds=min(len(offsets), 8))
    distance, fit = [], []
    try:
        for record in loaded.records:
            policy = loaded.policy(record.condition)
            distance.append(
                task.sample(policy_actor(policy, task.model), offsets).final_distance.tolist()
            )
            fit.append([_mean_fit(policy, r.samples) for r in loaded.records])
    finally:
        task.close()
    return {
        "conditions": [r.condition for r in loaded.records],
        "offsets": [list(o) for o in offsets],
        "success_threshold": loaded.info.task.world.success_threshold,
        "distance": distance,
        "fit": fit,
    }


def _mean_fit(policy: GaussianPolicy, samples: ConditionSamples) -> float:
    """The mean of :func:`fit_error` over a D_g (NaN when it is empty)."""
    if samples.x.shape[0] == 0:
        return math.nan
    return float(fit_error(policy, samples.x, samples.mean_cur, samples.prec_cur).mean())


def forgotten(table: dict[str, Any]) -> list[int]:
    """Conditions the policy succeeded at right after their own S-step and misses at the end."""
    threshold, distance = table["success_threshold"], table["distance"]
    return [
        c
        for j, c in enumerate(table["conditions"])
        if distance[j][j] < threshold <= distance[-1][j]
    ]


def plot_retention(table: dict[str, Any], path: str | Path, title: str) -> None:
    """Two panels, one line per training position against the S-step index: the policy's
    final distance (log scale, with the success threshold) and its fit error on the position's
    D_g. A marker opens each line at the position's own S-step. PNG, written atomically."""
    figure = Figure(figsize=(12, 4.6), dpi=100)
    FigureCanvasAgg(figure)
    left, right = figure.subplots(1, 2)
    steps = list(range(len(table["conditions"])))
    for j, condition in enumerate(table["conditions"]):
        colour = f"C{j % 10}"
        for ax, key in ((left, "distance"), (right, "fit")):
            values = [row[j] for row in table[key]]
            ax.plot(steps, values, color=colour, alpha=0.35, lw=1)
            ax.plot(steps[j:], values[j:], color=colour, lw=2, label=f"condition {condition}")
            ax.plot([j], [values[j]], "o", color=colour)
    left.axhline(table["success_threshold"], color="k", ls="--", lw=1, label="success threshold")
    left.set_yscale("log")
    left.set_ylabel("policy final distance (m)")
    right.set_yscale("log")
    right.set_ylabel("fit error on D_g (p_cur standard deviations)")
    for ax in (left, right):
        ax.set_xlabel("after the S-step of condition")
        ax.set_xticks(steps)
    left.legend(fontsize=7, loc="best")
    left.set_title("closed loop: where each position's rollout ends", fontsize=10)
    right.set_title("open loop: the policy against its teacher on D_g", fontsize=10)
    figure.suptitle(title, fontsize=11)
    figure.tight_layout()
    atomic_write(path, lambda tmp: figure.savefig(tmp, dpi=100, format="png"))
