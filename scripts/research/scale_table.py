"""How a stream's cost grows with the conditions learnt, from its metrics.jsonl.

    python scripts/research/scale_table.py --run DIR [--at 8 16 32] [--window 4]

For each ``--at`` count n, over the ``--window`` conditions ending at condition n (1-based):
the mean S-step time per condition (checks and repair rounds included), the mean repair
rounds, the replay's rows after condition n (D_g states summed over conditions 1..n; the
S-step also reads the augmented copies of the newest), the mean wall time per condition
(sampling, fits, C-steps and the S-step, from the recorded phase times), and the mean rollouts.
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (metrics.jsonl, summary.json)")
    parser.add_argument("--at", type=int, nargs="+", default=[8, 16, 32])
    parser.add_argument("--window", type=int, default=4)
    args = parser.parse_args()
    folder = RunFolder(args.run)
    records = folder.read_metrics()
    entries = folder.read_summary()["conditions"]
    distill = {r["condition"]: r for r in records if r.get("event") == "distilled"}
    phases: dict[int, float] = {}
    for r in records:
        if "iteration" in r:
            spent = r["time_sample"] + r["time_fit"] + r["time_cstep"]
            phases[r["condition"]] = phases.get(r["condition"], 0.0) + spent
    if max(args.at) > len(entries) or min(args.at) < args.window or args.window < 1:
        raise LolgpsError(f"--at must lie in [--window, {len(entries)}] for this run")
    print("| conditions learnt | S-step s/condition | repair rounds | replay rows | "
          "wall s/condition | rollouts/condition |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for n in args.at:
        window = range(n - args.window, n)
        sstep = sum(distill[c]["time_distill"] for c in window) / args.window
        repairs = sum(distill[c].get("repairs", 0) for c in window) / args.window
        rows = sum(distill[c]["distill_rows"] for c in range(n))
        wall = sum(phases.get(c, 0.0) + distill[c]["time_distill"] for c in window) / args.window
        rollouts = sum(entries[c]["rollouts"] for c in window) / args.window
        print(f"| {n} | {sstep:.2f} | {repairs:.2f} | {rows} | {wall:.2f} | {rollouts:.1f} |")


if __name__ == "__main__":
    run(main)
