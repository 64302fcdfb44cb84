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

from lolgps_torch.errors import LolgpsError


class Interval(NamedTuple):
    """An estimate with its confidence interval; ``low``/``high`` are None when undefined."""

    mean: float
    low: float | None
    high: float | None


def normal_quantile(p: float) -> float:
    """``z_p = Phi^{-1}(p)`` of the standard normal."""
    return statistics.NormalDist().inv_cdf(p)


def t_quantile(p: float, dof: int) -> float:
    """Student-t quantile ``t_{p, nu}`` for ``p > 1/2``.

    Closed form for ``nu = 1`` (``tan(pi (p - 1/2))``) and ``nu = 2``
    (``a sqrt(2 / (1 - a^2))``, ``a = 2p - 1``); for ``nu >= 3`` the Cornish-Fisher expansion
    of Abramowitz & Stegun 26.7.5, ``t = z + g1/nu + g2/nu^2 + g3/nu^3 + g4/nu^4`` with
    ``z = z_p`` (relative error below 2e-3 at ``p = 0.975``, falling as ``nu`` grows).
    """
    if dof < 1 or not 0.5 < p < 1.0:
        raise LolgpsError(f"t quantile needs dof >= 1 and 1/2 < p < 1, got dof {dof}, p {p}")
    if dof == 1:
        return math.tan(math.pi * (p - 0.5))
    if dof == 2:
        a = 2.0 * p - 1.0
        return a * math.sqrt(2.0 / (1.0 - a * a))
    z = normal_quantile(p)
    g1 = (z**3 + z) / 4.0
    g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96.0
    g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384.0
    g4 = (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160.0
    return z + g1 / dof + g2 / dof**2 + g3 / dof**3 + g4 / dof**4


def mean_ci(values: Sequence[float], confidence: float = 0.95) -> Interval:
    """Mean with the t interval ``m +- t_{(1+c)/2, n-1} s / sqrt(n)``, ``s`` the sample standard
    deviation (``n - 1`` in the denominator). The interval is None for ``n = 1``."""
    n = len(values)
    if n == 0:
        raise LolgpsError("mean of no values")
    mean = statistics.fmean(values)
    if n == 1:
        return Interval(mean, None, None)
    half = t_quantile((1.0 + confidence) / 2.0, n - 1) * statistics.stdev(values) / math.sqrt(n)
    return Interval(mean, mean - half, mean + half)


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
    mean final distance and mean total cost with their t intervals (:func:`mean_ci`) and the
    success rate with its Wilson interval (:func:`wilson_interval`), each as
    ``{"mean", "low", "high"}``."""
    rows = []
    for distance, cost, ok in zip(final_distance, total_cost, success, strict=True):
        rows.append(
            {
                "n": len(distance),
                "final_distance": mean_ci(distance, confidence)._asdict(),
                "total_cost": mean_ci(cost, confidence)._asdict(),
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


def forward_transfer(
    iterations: Sequence[int | None], scratch: Sequence[int | None]
) -> list[dict[str, float | int | None]]:
    """Forward transfer per condition from iterations to first success: the stream's ``n_c``
    against a from-scratch learner's ``n0_c``. ``ratio = n_c / n0_c`` (below 1: earlier
    conditions helped) and ``saved = n0_c - n_c`` (iterations saved, positive: helped); None
    where either count is unavailable (never succeeded, or no from-scratch run)."""
    rows: list[dict[str, float | int | None]] = []
    for n, n0 in zip(iterations, scratch, strict=True):
        ratio: float | None = None
        saved: int | None = None
        if n is not None and n0 is not None and n0 > 0:
            ratio, saved = n / n0, n0 - n
        rows.append({"iterations": n, "scratch_iterations": n0, "ratio": ratio, "saved": saved})
    return rows
