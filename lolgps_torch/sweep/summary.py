"""The aggregate over seeds of a sweep's finished cells (mean ± sd per method x arm x
stream x variant): summary.md, summary.csv and summary.png."""

from __future__ import annotations

import csv
import math
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lolgps_torch.data.run_folder import RunFolder, atomic_write, read_json
from lolgps_torch.lolgps.run import stream_config
from lolgps_torch.sweep.cells import CELL_FILE
from lolgps_torch.sweep.grid import Cell, Outcome, Sweep

# (key, markdown heading, format) of the aggregated metrics
METRICS = (
    ("train_success", "training success", ".2f"),
    ("test_success", "test-area success", ".2f"),
    ("forgetting_area0", "forgetting area 0", "+.2f"),
    ("forgetting_areas", "forgetting (mean)", "+.2f"),
    ("rollouts", "rollouts", ".0f"),
    ("wall_time", "wall time (s)", ".0f"),
)


def eval_metrics(evaluation: dict[str, Any]) -> dict[str, float | None]:
    """The headline test-area numbers of an eval.json: the final policy's success rate
    averaged over the test areas (``average_final_success``), and the forgetting of success
    on area 0 and its mean over the trained areas (positive: worse at the end than right after
    the stage that trained the area).

    :param evaluation: the parsed eval.json
    """
    metrics = evaluation["metrics"]
    forgot = (metrics.get("forgetting") or {}).get("success_rate") or {}
    per_area = forgot.get("per_area") or [None]
    return {
        "test_success": metrics.get("average_final_success"),
        "forgetting_area0": per_area[0],
        "forgetting_areas": forgot.get("mean"),
    }


def cell_metrics(folder: Path) -> dict[str, float | None] | None:
    """The per-run numbers of a cell folder, None if its run has not finished: the fraction of
    training positions where the final policy alone succeeds (``policy_success_end``), the
    rollouts (``sum of iterations x samples per iteration``), the sweep's wall time, and with
    an eval.json its :func:`eval_metrics`.

    :param folder: the cell folder
    """
    run = RunFolder(folder)
    if not run.summary_path.is_file():
        return None
    entries = run.read_summary()["conditions"]
    samples = stream_config(run, run.read_config()).local.samples
    row: dict[str, float | None] = {key: None for key, _, _ in METRICS}
    if entries:
        row["train_success"] = statistics.fmean(bool(e["policy_success_end"]) for e in entries)
    row["rollouts"] = float(sum(int(e["iterations"]) for e in entries) * samples)
    if (folder / CELL_FILE).is_file():
        row["wall_time"] = float(read_json(folder / CELL_FILE)["wall_time"])
    if run.eval_path.is_file():
        row.update(eval_metrics(read_json(run.eval_path)))
    return row


def mean_sd(values: Sequence[float | None]) -> tuple[float | None, float | None, int]:
    """Mean and sample standard deviation (``n - 1``) of the defined, finite ``values``, and
    their count; the sd is None below two values, both are None without any.

    :param values: one number per seed, None where unavailable
    """
    defined = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not defined:
        return None, None, 0
    sd = statistics.stdev(defined) if len(defined) > 1 else None
    return statistics.fmean(defined), sd, len(defined)


def aggregate(cells: Sequence[Cell], out: Path) -> list[dict[str, Any]]:
    """One row per method x arm x stream x variant, in grid order, over the seeds whose run
    finished: ``seeds`` (their count) and ``<metric>_mean``, ``<metric>_sd``, ``<metric>_n`` for each of
    :data:`METRICS`. Groups without a finished run are left out.

    :param cells: the grid
    :param out: the sweep folder holding the cell folders
    """
    groups: dict[tuple[str, str, str, str], list[dict[str, float | None]]] = {}
    for cell in cells:
        found = cell_metrics(out / cell.name)
        group = groups.setdefault((cell.method, cell.arm, cell.stream, cell.variant), [])
        if found is not None:
            group.append(found)
    rows = []
    for (method, arm, stream, variant), found_rows in groups.items():
        if not found_rows:
            continue
        row: dict[str, Any] = {"method": method, "arm": arm, "stream": stream, "variant": variant}
        row["seeds"] = len(found_rows)
        for key, _, _ in METRICS:
            mean, sd, n = mean_sd([r[key] for r in found_rows])
            row.update({f"{key}_mean": mean, f"{key}_sd": sd, f"{key}_n": n})
        rows.append(row)
    return rows


def format_mean_sd(mean: float | None, sd: float | None, fmt: str) -> str:
    """``mean ± sd`` in ``fmt`` (``-`` without a mean, the mean alone without an sd).

    :param mean: the mean, or None
    :param sd: the standard deviation, or None
    :param fmt: a format spec such as ``.2f``
    """
    if mean is None:
        return "-"
    if sd is None:
        return f"{mean:{fmt}}"
    return f"{mean:{fmt}} ± {sd:{fmt.lstrip('+')}}"


def markdown_table(rows: Sequence[dict[str, Any]], failed: Sequence[Outcome]) -> str:
    """The aggregate as a markdown table, mean ± sd over seeds, with the failed cells after it.

    :param rows: from :func:`aggregate`
    :param failed: the cells that failed in this sweep
    """
    keys = ["method", "arm", "stream"] + (["variant"] if any(r["variant"] for r in rows) else [])
    heads = [*keys, "seeds", *(head for _, head, _ in METRICS)]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for row in rows:
        cells = [*(row[k] for k in keys), str(row["seeds"])]
        cells += [format_mean_sd(row[f"{k}_mean"], row[f"{k}_sd"], f) for k, _, f in METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Mean ± sd over seeds. Training success: fraction of training positions where the final "
        "policy alone succeeds. Test-area success: the final policy's success rate averaged "
        "over the test areas (eval.json). Forgetting: drop in success rate between the stage "
        "that trained an area and the end (positive: forgot). Rollouts: iterations x samples.",
    ]
    if failed:
        lines += ["", "Failed cells:", ""]
        lines += [f"- `{o.cell.name}`: {o.error}" for o in failed]
    return "\n".join(lines) + "\n"


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """The aggregate as CSV: method, arm, stream, variant, seeds, then mean, sd and n per
    metric.

    :param path: the file
    :param rows: from :func:`aggregate`
    """
    fields = ["method", "arm", "stream", "variant", "seeds"]
    fields += [f"{k}_{s}" for k, _, _ in METRICS for s in ("mean", "sd", "n")]

    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=fields)
            writer.writeheader()
            for row in rows:
                writer.writerow({f: "" if row[f] is None else row[f] for f in fields})

    atomic_write(path, write)


def plot_summary(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """Bar charts of training success and rollouts per method x arm (x stream x variant), with
    sd error bars, saved to ``path``.

    :param path: the image file
    :param rows: from :func:`aggregate`
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    streams = {row["stream"] for row in rows}
    labels = [
        f"{r['method']}\n{r['arm']}"
        + (f"\n{r['stream']}" if len(streams) > 1 else "")
        + (f"\n{r['variant']}" if r["variant"] else "")
        for r in rows
    ]
    fig, axes = plt.subplots(1, 2, figsize=(max(6.0, 1.6 * len(rows) + 2.0), 3.8))
    for ax, (key, title) in zip(
        axes, (("train_success", "training success"), ("rollouts", "rollouts")), strict=True
    ):
        means = [row[f"{key}_mean"] or 0.0 for row in rows]
        sds = [row[f"{key}_sd"] or 0.0 for row in rows]
        ax.bar(range(len(rows)), means, yerr=sds, capsize=4, color="tab:blue")
        ax.set_xticks(range(len(rows)), labels, fontsize=8)
        ax.set_title(f"{title} (mean ± sd over seeds)", fontsize=9)
    axes[0].set_ylim(0.0, 1.05)
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
    plt.close(fig)


def write_summaries(sweep: Sweep, failed: Sequence[Outcome]) -> list[Path]:
    """Write summary.md, summary.csv and (with any finished run) summary.png into the sweep
    folder and return their paths.

    :param sweep: the sweep
    :param failed: the cells that failed in this sweep
    """
    out = Path(sweep.plan.out)
    rows = aggregate(sweep.cells, out)
    text = markdown_table(rows, failed)
    atomic_write(out / "summary.md", lambda tmp: tmp.write_text(text))
    write_csv(out / "summary.csv", rows)
    written = [out / "summary.md", out / "summary.csv"]
    if rows:
        plot_summary(out / "summary.png", rows)
        written.append(out / "summary.png")
    return written
