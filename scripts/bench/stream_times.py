"""Phase times of finished streams, summed from their metrics.jsonl, beside their outcome.

    python scripts/bench/stream_times.py RUN [RUN ...]

One markdown row per run folder: the final policy's successes at the training positions
(summary.json), the seconds ``metrics.jsonl`` records for sampling, dynamics fits, C-steps
(with the C-steps planned on the model) and S-steps (each S-step with its closed-loop check
and repair rounds), the repair rounds, and the S-steps' time over the sampling time. The times are wall seconds of each phase, so
on a shared machine compare the ratio, not the seconds.
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder

PHASES = ("time_sample", "time_fit", "time_cstep", "time_distill")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="finished run folders")
    args = parser.parse_args()
    print(
        "| run | final | sampling s | fits s | C-steps s | S-steps s | repair rounds "
        "| S-steps / sampling |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for path in args.runs:
        folder = RunFolder(path)
        sums = dict.fromkeys(PHASES, 0.0)
        repairs = 0
        for record in folder.read_metrics():
            for phase in PHASES:
                sums[phase] += float(record.get(phase, 0.0))
            repairs += int(record.get("repairs") or 0)
        entries = folder.read_summary()["conditions"]
        final = sum(bool(e["policy_success_end"]) for e in entries)
        times = " | ".join(f"{sums[p]:.1f}" for p in PHASES)
        ratio = sums["time_distill"] / sums["time_sample"] if sums["time_sample"] else float("nan")
        print(
            f"| {folder.path.name} | {final}/{len(entries)} | {times} | {repairs} | {ratio:.2f} |"
        )


if __name__ == "__main__":
    run(main)
