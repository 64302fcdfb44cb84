"""Where a finished run's transfer probes ended: how far the peg missed, sideways and in height.

    python scripts/research/probe_miss.py --run DIR [DIR ...]

The probe at condition m (m >= 1) is the policy checkpointed after condition m - 1, rolled out
once without noise at m's hole (docs/ALGORITHM.md section 8). It is repeated here, and its
last state gives the peg tip's position relative to the hole-floor target: the lateral miss
(the tip's horizontal distance from the hole's axis) and the height above the floor, beside
the final distance the stream judges success by. Prints one markdown row per probe.
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import policy_actor


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", nargs="+", required=True, help="finished run folders")
    args = parser.parse_args()
    print("| run | condition | final distance (m) | lateral miss (mm) | height above floor (mm) |")
    print("|---|---|---|---|---|")
    for path in args.run:
        loaded = load_run(path)
        task = loaded.make_task(n_worlds=1)
        try:
            tip = task.layout.points.start  # the tip's (x, y, z) come first, relative to target
            for record in loaded.records[1:]:
                policy = loaded.policy(record.condition - 1)
                probe = task.sample(policy_actor(policy), [record.offset])
                error = probe.final_state[0, tip : tip + 3]
                lateral = 1000.0 * float(error[:2].norm())
                print(
                    f"| {path} | {record.condition} | {float(probe.final_distance[0]):.3f} | "
                    f"{lateral:.1f} | {1000.0 * float(error[2]):.1f} |",
                    flush=True,
                )
        finally:
            task.close()


if __name__ == "__main__":
    run(main)
