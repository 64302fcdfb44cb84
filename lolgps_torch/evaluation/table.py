"""The evaluation as a plain-text table (what ``scripts/evaluate.py`` prints)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any


def format_table(evaluation: dict[str, Any]) -> str:
    """A plain-text table: per stage and group, distance, cost and success with 95% CIs, the
    largest joint speed over its velocity limit and the faults (NaN and - for an evaluation
    that did not record them)."""

    def interval(stat: dict[str, float | None], fmt: str) -> str:
        if stat["low"] is None or stat["high"] is None:
            return f"{stat['mean']:{fmt}}"
        return f"{stat['mean']:{fmt}} [{stat['low']:{fmt}}, {stat['high']:{fmt}}]"

    lines = [
        f"{'stage':<8} {'group':<18} {'centre (m)':>10}  {'final distance (m)':<26} "
        f"{'total cost':<28} {'success':<18} peak speed / limit  faults"
    ]
    for stage in evaluation["stages"]:
        for group, stats in zip(evaluation["groups"], stage["groups"], strict=True):
            lines.append(
                f"{stage['name']:<8} {group['label']:<18} {group['centre_distance']:>10.3f}  "
                f"{interval(stats['final_distance'], '.4f'):<26} "
                f"{interval(stats['total_cost'], '.1f'):<28} "
                f"{interval(stats['success_rate'], '.2f'):<18} "
                f"{stats.get('peak_speed', math.nan):>18.2f}  {stats.get('faults', '-')}"
            )
    metrics = evaluation["metrics"]
    lines.append(f"average final success: {metrics['average_final_success']:.3f}")
    if metrics["forgetting"] is not None:
        for name, forgot in metrics["forgetting"].items():
            cells = ["  -  " if v is None else f"{v:+.3g}" for v in forgot["per_area"]]
            lines.append(f"forgetting of {name} per area (positive: worse): {' '.join(cells)}")
    if metrics["forward_transfer"] is not None:
        lines.append(f"{'condition':>9} {'rollouts':>8} {'AUC':>6} {'scratch':>7} {'FT':>6}")
        for row in metrics["forward_transfer"]:
            cells = [_cell(row[k], ".3f") for k in ("auc", "scratch_auc", "forward_transfer")]
            lines.append(
                f"{row['condition']:>9} {_cell(row['rollouts'], 'd'):>8} "
                f"{cells[0]:>6} {cells[1]:>7} {cells[2]:>6}"
            )
        mean = metrics["mean_forward_transfer"]
        lines.append(f"mean forward transfer (conditions 1..): {_cell(mean, '.3f')}")
    return "\n".join(lines)


def _cell(value: float | int | None, fmt: str) -> str:
    return "-" if value is None else f"{value:{fmt}}"


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A Markdown table: the header, its rule, then one line per row of cells."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cells) + " |" for cells in rows]
    return "\n".join(lines)
