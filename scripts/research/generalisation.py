"""How far from its training positions the global policy still inserts, over evaluated runs.

    python scripts/research/generalisation.py SWEEP_OR_RUN ... [--stage train2]
        [--bins 0.01 0.02 0.03 0.05 0.1] [--plan N]

For every test position of ``eval.json`` after ``--stage``: its distance to the nearest
position trained by that stage, and whether the policy's noiseless rollout inserted there. The
table gives the success rate per distance bin over all runs, and per run the nearest missed
test position and how many misses lie within the first bins, so a miss beside a training
position (the fit's imprecision) is told from a miss far from every one (extrapolation).

``--plan N`` then takes each run's N missed test positions nearest to a training position and
plans the first controller there on the arm's model, as the stream does at a new condition
(no sample and no policy involved), and samples it once in the simulator with its exploration
noise (the run's samples per iteration): how often a teacher planned on the model inserts where
the policy misses.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import evaluated_runs
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import LocalLearner
from lolgps_torch.lolgps.run import load_run


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", help="sweep or run folders")
    parser.add_argument("--stage", default="train2", help="stage of the test (%(default)s)")
    parser.add_argument(
        "--bins", type=float, nargs="+", default=[0.01, 0.02, 0.03, 0.05, 0.1],
        help="upper edges (m) of the distance bins (%(default)s)",
    )  # fmt: skip
    parser.add_argument("--plan", type=int, default=0, help="misses per run to plan at (0)")
    args = parser.parse_args()
    if any(b <= 0 for b in args.bins) or sorted(args.bins) != args.bins:
        raise LolgpsError(f"--bins {args.bins}: positive and increasing")
    if args.plan < 0:
        raise LolgpsError(f"--plan {args.plan}: must be >= 0")
    return args


def test_positions(folder: Path, stage: str) -> tuple[list[list[float]], list[float], list[bool]]:
    """Each test position after ``stage``, its distance (m) to the nearest position trained by
    then, and whether the policy inserted there."""
    evaluation = json.loads((folder / "eval.json").read_text())
    stages = [s["name"] for s in evaluation["stages"]]
    if stage not in stages:
        raise LolgpsError(f"{folder}: no stage {stage!r} in eval.json (has {stages})")
    index = stages.index(stage)
    result = evaluation["stages"][index]
    trained = evaluation["training"]["conditions"][: result["last_condition"] + 1]
    positions, nearest, success = [], [], []
    for group, hits in zip(evaluation["groups"], result["per_position"]["success"], strict=True):
        for p, hit in zip(group["positions"], hits, strict=True):
            positions.append(p)
            nearest.append(min(math.dist(p, c) for c in trained))
            success.append(bool(hit))
    return positions, nearest, success


def bin_of(distance: float, bins: list[float]) -> int:
    """The index of the first bin whose upper edge exceeds ``distance`` (len(bins): beyond)."""
    return next((i for i, edge in enumerate(bins) if distance < edge), len(bins))


def planned_teachers(folder: Path, misses: list[list[float]]) -> tuple[int, int]:
    """Successful rollouts and rollouts of the first controller planned on the model at each of
    ``misses``, sampled once with its exploration noise."""
    loaded = load_run(folder)
    task = loaded.make_task(loaded.info.stream.local.samples)
    good = total = 0
    try:
        for k, p in enumerate(misses):
            learner = LocalLearner(task, (p[0], p[1]), loaded.info.stream.local, seed=k)
            samples = learner.sample(learner.p_cur)
            good, total = good + int(samples.success.sum()), total + int(samples.success.numel())
    finally:
        task.close()
    return good, total


def main() -> None:
    args = parse_args()
    warnings.simplefilter("ignore", UserWarning)  # the planning's KL warnings, as in the stream
    bins = args.bins
    labels = [f"< {bins[0] * 100:g} cm"]
    labels += [f"{lo * 100:g}-{hi * 100:g} cm" for lo, hi in zip(bins, bins[1:], strict=False)]
    labels += [f">= {bins[-1] * 100:g} cm"]
    folders = [f for arg in args.folders for f in evaluated_runs(arg)]
    hits = [0] * len(labels)
    counts = [0] * len(labels)
    print("| run | misses | nearest miss (cm) | " + " | ".join(f"misses {b}" for b in labels[:3])
          + " | planned teachers at its nearest misses |")  # fmt: skip
    print("|---" * 7 + "|")
    for folder in folders:
        positions, nearest, success = test_positions(folder, args.stage)
        missed = sorted(
            (d, p) for p, d, s in zip(positions, nearest, success, strict=True) if not s
        )
        per_bin = [0] * len(labels)
        for d, s in zip(nearest, success, strict=True):
            b = bin_of(d, bins)
            counts[b] += 1
            hits[b] += s
            per_bin[b] += not s
        planned = "-"
        if args.plan and missed:
            good, total = planned_teachers(folder, [p for _, p in missed[: args.plan]])
            planned = f"{good}/{total} rollouts insert"
        first = f"{missed[0][0] * 100:.1f}" if missed else "-"
        print(f"| {folder.name} | {len(missed)} | {first} | "
              + " | ".join(str(n) for n in per_bin[:3]) + f" | {planned} |", flush=True)  # fmt: skip
    print()
    print("| distance to the nearest trained position | test positions | success |")
    print("|---|---|---|")
    for label, n, h in zip(labels, counts, hits, strict=True):
        rate = f"{100 * h / n:.1f} %" if n else "-"
        print(f"| {label} | {n} | {rate} |")


if __name__ == "__main__":
    torch.set_num_threads(1)
    run(main)
