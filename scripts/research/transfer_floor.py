"""How far forward transfer can lower a stream's later rollouts, per finished run.

    python scripts/research/transfer_floor.py RUN [RUN ...] [--size K]

A condition where the policy's probe succeeds costs the probe and ``transfer_phases``
iterations of N samples, ``1 + transfer_phases N`` rollouts (the floor); any other costs at
least ``success_phases N``. Per run, from its config.json and summary.json: the conditions that
transferred (ended at the floor) and their share; the rollouts of the first ``K`` and of the
last ``K`` conditions and their ratio; and the floor ratio, ``K x floor / rollouts of the
first K``: the ratio if every one of the last K transferred. A stream whose floor ratio is
above a target cannot reach it by transferring more conditions, only by a lower floor.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.table import markdown_table
from lolgps_torch.lolgps.run import read_run


def row(path: Path, size: int) -> list[str]:
    """The table's cells for the run at ``path``, comparing its first and last ``size``
    conditions."""
    folder = RunFolder(path)
    stream = read_run(folder).stream
    floor = 1 + stream.transfer_phases * stream.local.samples
    rollouts = [int(c["rollouts"]) for c in folder.read_summary()["conditions"]]
    if len(rollouts) < 2 * size:
        raise LolgpsError(f"{path}: {len(rollouts)} conditions, fewer than 2 x --size {size}")
    transferred = sum(r == floor for r in rollouts)
    early, late = sum(rollouts[:size]), sum(rollouts[-size:])
    return [
        path.name,
        f"{transferred}/{len(rollouts)}",
        f"{floor}",
        f"{early} / {late} ({late / early:.2f})",
        f"{size * floor / early:.2f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    parser.add_argument("--size", type=int, default=4, help="conditions per group (default 4)")
    args = parser.parse_args()
    if args.size < 1:
        raise LolgpsError(f"--size {args.size}: must be at least 1")
    header = (
        "run", "transferred", "floor (rollouts)", "first K / last K", "floor ratio",
    )  # fmt: skip
    print(markdown_table(header, (row(path, args.size) for path in args.runs)))


if __name__ == "__main__":
    run(main)
