"""How far the final policy's success extends around its training positions.

    python scripts/research/robustness.py --run DIR [DIR ...] [--mm 4] [--directions 8]

For each run, the final global policy runs noiselessly with the hole moved by ``--mm``
millimetres from each training position, in ``--directions`` directions evenly spread around
it (starting along +x). Prints, per run, the positions reached out of 8 x directions, then
the training positions at which any moved hole was missed, with the misses' largest final
distance. A policy that only just reaches its training positions (a knife-edged closed
loop) shows here as misses a few millimetres away.
"""

from __future__ import annotations

import argparse
import math

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.lolgps.stream import policy_distances


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", nargs="+", required=True, help="finished run folders")
    parser.add_argument("--mm", type=float, default=4.0, help="hole displacement (%(default)s)")
    parser.add_argument("--directions", type=int, default=8, help="(%(default)s)")
    args = parser.parse_args()
    if args.directions < 1 or not 0.0 < args.mm < 1000.0:
        raise LolgpsError("--directions must be >= 1 and --mm in (0, 1000)")
    return args


def main() -> None:
    args = parse_args()
    radius = args.mm / 1000.0
    angles = [2.0 * math.pi * k / args.directions for k in range(args.directions)]
    for path in args.run:
        loaded = load_run(path)
        offsets = [record.offset for record in loaded.records]
        moved = [
            (x + radius * math.cos(a), y + radius * math.sin(a)) for x, y in offsets for a in angles
        ]
        task = loaded.make_task()
        try:
            distances = policy_distances(task, loaded.policy(), moved)
        finally:
            task.close()
        threshold = task.config.world.success_threshold
        reached = sum(d < threshold for d in distances)
        misses = []
        for i in range(len(offsets)):
            own = distances[i * args.directions : (i + 1) * args.directions]
            missed = [d for d in own if not d < threshold]
            if missed:
                misses.append(f"{i} ({len(missed)} missed, up to {max(missed):.3f} m)")
        print(
            f"{path}: {reached}/{len(moved)} ({reached / len(moved):.0%}) reached "
            f"{args.mm:g} mm around the training positions; misses at "
            + (", ".join(misses) if misses else "none")
        )


if __name__ == "__main__":
    run(main)
