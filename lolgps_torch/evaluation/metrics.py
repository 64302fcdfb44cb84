"""Statistics of the Fig. 4 evaluation and the continual-learning metrics (Continual World).

Results are grouped: a group is a test area (or, with explicit positions, one position), and
stages are the training stages whose checkpoints were evaluated, in stream order. Lists indexed
``[s][g]`` are stage-first. Everything here is plain arithmetic on numbers, with no simulator.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from lolgps_torch.errors import LolgpsError


class Interval(NamedTuple):
    """An estimate with its confidence interval; ``low``/``high`` are None when undefined."""

    mean: float
    low: float | None
    high: float | None


def normal_quantile(p: float) -> float:
    """``z_p = Phi^{-1}(p)`` of the standard normal."""
    return statistics.NormalDist().inv_cdf(p)


BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def bootstrap_mean_ci(
    values: Sequence[float],
    confidence: float = 0.95,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> Interval:
    """Mean with the percentile bootstrap interval (Efron & Tibshirani 1993, ch. 13): the
    ``(1 - c)/2`` and ``(1 + c)/2`` quantiles of the means of ``resamples`` samples of size
    ``n`` drawn with replacement from ``values``, with a fixed ``seed`` so a result reads the
    same every time. Every resampled mean lies within ``[min, max]`` of the values, so the
    interval respects their support: non-negative for distances, unlike ``m +- t s/sqrt(n)``,
    which goes below zero for a few small distances and one large one. The interval is None
    for ``n = 1``."""
    n = len(values)
    if n == 0:
        raise LolgpsError("mean of no values")
    if resamples < 1 or not 0.0 < confidence < 1.0:
        raise LolgpsError(
            f"bootstrap needs resamples >= 1 and 0 < confidence < 1, got {resamples}, {confidence}"
        )
    sample = np.asarray(values, dtype=np.float64)
    mean = float(sample.mean())
    if n == 1:
        return Interval(mean, None, None)
    rows = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    means = sample[rows].mean(axis=1)  # [resamples]
    low, high = np.quantile(means, [(1.0 - confidence) / 2.0, (1.0 + confidence) / 2.0])
    return Interval(mean, float(low), float(high))


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> Interval:
    """Success rate ``p = k / n`` with the Wilson score interval
    ``(p + z^2/2n +- z sqrt(p (1 - p)/n + z^2/4n^2)) / (1 + z^2/n)``, ``z = z_{(1+c)/2}``;
    unlike the normal interval it stays inside [0, 1] and is not empty at ``p`` = 0 or 1."""
    if n < 1 or not 0 <= successes <= n:
        raise LolgpsError(f"success rate needs 0 <= successes <= n, n >= 1, got {successes}/{n}")
    p = successes / n
    z = normal_quantile((1.0 + confidence) / 2.0)
    denominator = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n)) / denominator
    return Interval(p, max(0.0, centre - half), min(1.0, centre + half))


def aggregate(
    final_distance: Sequence[Sequence[float]],
    total_cost: Sequence[Sequence[float]],
    success: Sequence[Sequence[bool]],
    confidence: float = 0.95,
) -> list[dict[str, Any]]:
    """Per group ``g`` (one stage's results, each argument indexed ``[g][position]``): ``n``, the
    mean final distance and mean total cost with their bootstrap intervals
    (:func:`bootstrap_mean_ci`) and the success rate with its Wilson interval
    (:func:`wilson_interval`), each as ``{"mean", "low", "high"}``."""
    rows = []
    for distance, cost, ok in zip(final_distance, total_cost, success, strict=True):
        rows.append(
            {
                "n": len(distance),
                "final_distance": bootstrap_mean_ci(distance, confidence)._asdict(),
                "total_cost": bootstrap_mean_ci(cost, confidence)._asdict(),
                "success_rate": wilson_interval(sum(map(bool, ok)), len(ok), confidence)._asdict(),
            }
        )
    return rows


def first_training_stage(
    condition_groups: Sequence[int], stages: Sequence[Mapping[str, Any]], n_groups: int
) -> list[int | None]:
    """Per group, the index of the first stage with a condition in it (None: never trained).

    Condition ``c`` belongs to stage ``s`` when ``last_{s-1} < c <= last_s`` (``last`` the
    stages' ``last_condition``); ``condition_groups[c]`` is its group, -1 for none."""
    trained: list[int | None] = [None] * n_groups
    first = 0
    for s, stage in enumerate(stages):
        last = int(stage["last_condition"])
        for group in condition_groups[first : last + 1]:
            if 0 <= group < n_groups and trained[group] is None:
                trained[group] = s
        first = last + 1
    return trained


def forgetting(
    values: Sequence[Sequence[float]],
    trained_stage: Sequence[int | None],
    higher_is_better: bool,
) -> list[float | None]:
    """Forgetting per group (Continual World): ``F_g = v[s_g][g] - v[S-1][g]`` for a metric where
    higher is better (success rate), ``F_g = v[S-1][g] - v[s_g][g]`` where lower is better
    (distance, cost), so that positive always means worse at the end than right after stage
    ``s_g``, the one that trained ``g`` (``trained_stage[g]``, an index into ``values``).
    None where the group was never trained or its training stage was not evaluated."""
    end = values[-1]
    sign = 1.0 if higher_is_better else -1.0
    return [
        None if s is None else sign * (float(values[s][g]) - float(end[g]))
        for g, s in enumerate(trained_stage)
    ]


def mean_defined(values: Sequence[float | None]) -> float | None:
    """Mean of the values that are not None (None if there are none)."""
    defined = [v for v in values if v is not None]
    return statistics.fmean(defined) if defined else None


def average_final_success(final_success_rate: Sequence[float]) -> float:
    """``A = (1/G) sum_g p_g``: the last stage's success rate averaged over the groups."""
    if not final_success_rate:
        raise LolgpsError("average success of no groups")
    return statistics.fmean(final_success_rate)
