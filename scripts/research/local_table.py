"""The local learner's outcome per finished stream run, one Markdown row per run.

    python scripts/research/local_table.py RUN [RUN ...]

From each run's summary.json and metrics.jsonl: the global policy's successes at the training
positions at the end; the local controllers (each condition's final p_cur, noiseless) within
the success threshold, and the worst one's distance (m) with its condition; the mean first
iteration with a successful sample; iterations summed over conditions; and the summed fit and
C-step times as ratios to the summed sampling time (``time_fit`` holds the dynamics fit, the
cost expansion, the step adaptation and p_pre's fit).
"""

from __future__ import annotations

import argparse
import statistics

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.evaluation.table import markdown_table
from lolgps_torch.lolgps.run import read_run


def row(path: str) -> list[str]:
    """The table's cells for one run."""
    folder = RunFolder(path)
    conditions = folder.read_summary()["conditions"]
    threshold = read_run(folder).task.world.success_threshold
    local = [float(c["local_final_distance"]) for c in conditions]
    worst = max(range(len(local)), key=lambda i: local[i])
    first = [c["first_success_iteration"] for c in conditions]
    found = [f for f in first if f is not None]
    times = {"time_sample": 0.0, "time_fit": 0.0, "time_cstep": 0.0}
    for record in folder.read_metrics():
        if "time_fit" in record:
            for key in times:
                times[key] += float(record[key])
    sample = times["time_sample"]
    return [
        path,
        f"{sum(bool(c['policy_success_end']) for c in conditions)}/{len(conditions)}",
        f"{sum(d < threshold for d in local)}/{len(local)}",
        f"{local[worst]:.4f} ({worst})",
        f"{statistics.fmean(found) if found else float('nan'):.1f}",
        f"{sum(int(c['iterations']) for c in conditions)}",
        f"{times['time_fit'] / sample:.2f}",
        f"{times['time_cstep'] / sample:.2f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+")
    args = parser.parse_args()
    header = (
        "run", "policy at the positions (end)", "local controllers within threshold",
        "worst local (m, condition)", "first success (mean iteration)", "iterations",
        "fit / sampling", "C-step / sampling",
    )  # fmt: skip
    print(markdown_table(header, (row(path) for path in args.runs)))


if __name__ == "__main__":
    run(main)
