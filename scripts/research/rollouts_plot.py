"""Rollouts per condition along a stream: does a later condition cost less than an earlier one?

    python scripts/research/rollouts_plot.py RUN [RUN ...] --out FIGURE.png

One line per run (its folder name as the label): the rollouts drawn at each condition, in
the order the conditions arrived, from the run's summary.json. Forward transfer shows as a
falling line; a flat line means every condition was learnt as if it were the first.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder, atomic_write


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    parser.add_argument("--out", required=True, type=Path, help="the figure (PNG)")
    args = parser.parse_args()
    figure = Figure(figsize=(7.0, 3.5))
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    for path in args.runs:
        rollouts = [int(c["rollouts"]) for c in RunFolder(path).read_summary()["conditions"]]
        axes.plot(range(len(rollouts)), rollouts, marker=".", label=path.name)
    axes.set_xlabel("condition (order of arrival)")
    axes.set_ylabel("rollouts")
    axes.set_ylim(bottom=0)
    axes.legend(fontsize="small")
    figure.tight_layout()
    atomic_write(args.out, lambda tmp: figure.savefig(tmp, format="png", dpi=120))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    run(main)
