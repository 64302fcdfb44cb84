"""Figures of an evaluation (the dict :func:`lolgps_torch.evaluation.evaluate.evaluate_run`
writes): paper Fig. 4 (distance and cost against the test area's distance, one curve per stage)
beside a Fig. 3 style map of the training and test positions.

Drawn on an Agg canvas without pyplot, so no global backend state changes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from lolgps_torch.data.run_folder import atomic_write


def _errors(stats: Sequence[dict[str, Any]]) -> list[list[float]]:
    """Matplotlib's asymmetric error bars ``[[mean - low], [high - mean]]`` (0 if undefined)."""
    below = [s["mean"] - s["low"] if s["low"] is not None else 0.0 for s in stats]
    above = [s["high"] - s["mean"] if s["high"] is not None else 0.0 for s in stats]
    return [below, above]


def _stage_colours(evaluation: dict[str, Any]) -> dict[str, str]:
    """One colour per training stage, fixed by the stage's place in the stream."""
    return {s["name"]: f"C{i}" for i, s in enumerate(evaluation["training"]["stages"])}


def _draw_curves(ax: Axes, evaluation: dict[str, Any], colours: dict[str, str]) -> None:
    """Fig. 4: mean final distance (solid, left axis) and mean total cost (dashed, right axis)
    per stage against the groups' centre distance, with 95% CIs as error bars."""
    order = sorted(
        range(len(evaluation["groups"])), key=lambda g: evaluation["groups"][g]["centre_distance"]
    )
    x = [evaluation["groups"][g]["centre_distance"] for g in order]
    cost_ax = ax.twinx()
    for stage in evaluation["stages"]:
        colour = colours.get(stage["name"], "k")
        rows = [stage["groups"][g] for g in order]
        for axis, key, style, label in (
            (ax, "final_distance", "-", "distance"),
            (cost_ax, "total_cost", "--", "cost"),
        ):
            stats = [r[key] for r in rows]
            axis.errorbar(
                x,
                [s["mean"] for s in stats],
                yerr=_errors(stats),
                color=colour,
                linestyle=style,
                marker="o",
                markersize=3,
                capsize=2,
                label=f"{label}_{stage['name']}",
            )
    ax.axhline(
        evaluation["success_threshold"],
        color="0.5",
        linestyle=":",
        linewidth=1,
        label="success threshold",
    )
    what = "test position" if evaluation["mode"] == "positions" else "test area's centre"
    ax.set_xlabel(f"distance of the {what} from the nominal hole (m)")
    ax.set_ylabel("mean final tip distance (m)")
    cost_ax.set_ylabel("mean total cost")
    handles, labels = ax.get_legend_handles_labels()
    cost_handles, cost_labels = cost_ax.get_legend_handles_labels()
    ax.legend(handles + cost_handles, labels + cost_labels, fontsize=7, loc="best", ncol=2)
    ax.set_title("Fig. 4: performance against test distance", fontsize=10)


def _draw_map(
    ax: Axes,
    evaluation: dict[str, Any],
    colours: dict[str, str],
    conditions: Sequence[Sequence[float]],
) -> None:
    """Fig. 3: test-area circles, the test positions faintly (explicit positions as open
    circles), the training positions coloured by stage. The areas' axis runs horizontally."""
    area_config = evaluation.get("area_config") or {}
    h, v = (1, 0) if area_config.get("axis", "y") == "y" else (0, 1)
    names = "xy"
    for group in evaluation["groups"]:
        points = group["positions"]
        if group["radius"] is None:
            ax.scatter(
                [p[h] for p in points],
                [p[v] for p in points],
                s=30,
                marker="o",
                facecolors="none",
                edgecolors="0.4",
                linewidths=0.8,
            )
            continue
        ax.scatter(
            [p[h] for p in points],
            [p[v] for p in points],
            s=4,
            color="0.6",
            alpha=0.5,
            linewidths=0,
        )
        centre = (group["centre"][h], group["centre"][v])
        ax.add_patch(Circle(centre, group["radius"], fill=False, edgecolor="0.3", linewidth=0.8))
    first = 0
    for stage in evaluation["training"]["stages"]:
        last = stage["last_condition"]
        chosen = conditions[first : last + 1]
        ax.scatter(
            [c[h] for c in chosen],
            [c[v] for c in chosen],
            s=25,
            marker="x",
            color=colours[stage["name"]],
            label=stage["name"],
            zorder=3,
        )
        first = last + 1
    ax.plot(
        [0.0], [0.0], marker="+", color="k", markersize=8, linestyle="none", label="nominal hole"
    )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"hole offset d{names[h]} (m)")
    ax.set_ylabel(f"hole offset d{names[v]} (m)")
    ax.legend(fontsize=7, loc="best")
    ax.set_title("Fig. 3: training and test positions", fontsize=10)


def plot_fig4(
    evaluation: dict[str, Any],
    path: str | Path,
    conditions: Sequence[Sequence[float]] | None = None,
) -> None:
    """Write the two-panel figure to ``path`` (PNG, 100 dpi, written atomically).

    :param evaluation: the evaluation dict (as in ``eval.json``).
    :param conditions: training positions ``[[dx, dy], ...]`` in stream order (default: those
        of the evaluation's run).
    """
    colours = _stage_colours(evaluation)
    if conditions is None:
        conditions = evaluation["training"]["conditions"]
    figure = Figure(figsize=(12, 4.8), dpi=100)
    FigureCanvasAgg(figure)
    curves, layout = figure.subplots(1, 2, gridspec_kw={"width_ratios": [1.3, 1.0]})
    _draw_curves(curves, evaluation, colours)
    _draw_map(layout, evaluation, colours, conditions)
    figure.suptitle(f"{evaluation['method']} (seed {evaluation['seed']})", fontsize=11)
    figure.tight_layout()
    atomic_write(path, lambda tmp: figure.savefig(tmp, dpi=100, format="png"))
