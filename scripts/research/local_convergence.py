"""When a condition's local learning has converged, against when the stream stops it.

    python scripts/research/local_convergence.py RUN_OR_SWEEP ... [--within 0.02]

For every condition of every run (a run folder, or a sweep folder of them) that was learnt
from its hold controller to ``success_phases`` iterations (no forward transfer), from its
``metrics.jsonl``: the iteration from which the samples' mean cost stays within ``--within``
of the condition's last iteration (relative), the first iteration whose samples all succeed,
and the iterations run. Then, over all of them, how many iterations each count of phases
would have kept past convergence, and the arm rollouts (5 samples an iteration) they cost.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import NamedTuple

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import CONFIG_FILE, read_json, runs_holding


class Condition(NamedTuple):
    """One condition learnt without transfer: its run and index, the iterations run, the first
    iteration at which the cost stays within the tolerance of the last, and the first whose
    samples all succeed (-1: none)."""

    run: str
    condition: int
    iterations: int
    settled: int
    all_succeed: int
    costs: tuple[float, ...]


def settled_at(costs: list[float], within: float) -> int:
    """The first iteration from which every mean cost lies within ``within`` (relative) of
    the last one."""
    last = costs[-1]
    settled = len(costs) - 1
    for i in range(len(costs) - 1, -1, -1):
        if abs(costs[i] - last) > within * abs(last):
            break
        settled = i
    return settled


def conditions(folder: Path, within: float) -> list[Condition]:
    """The conditions of the run ``folder`` that ran ``success_phases`` iterations."""
    config = read_json(folder / CONFIG_FILE)
    phases = config["stream"]["success_phases"]
    rows: dict[int, list[dict[str, float]]] = {}
    for line in (folder / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if "iteration" in record and "mean_cost" in record:
            rows.setdefault(record["condition"], []).append(record)
    found = []
    for index, records in sorted(rows.items()):
        if len(records) < phases:
            continue  # forward transfer stopped it early
        costs = [r["mean_cost"] for r in records]
        succeed = [i for i, r in enumerate(records) if r["success_rate"] >= 1.0]
        found.append(
            Condition(
                folder.name, index, len(records), settled_at(costs, within),
                succeed[0] if succeed else -1, tuple(costs),
            )
        )  # fmt: skip
    return found


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--within", type=float, default=0.02)
    args = parser.parse_args()
    folders = [f for path in args.runs for f in runs_holding(path, CONFIG_FILE, "run")]
    found = [c for folder in folders for c in conditions(folder, args.within)]
    print(f"{'run':40} cond iters settled all-succeed  mean cost by iteration")
    for c in found:
        costs = " ".join(f"{v:.3f}" for v in c.costs)
        print(
            f"{c.run:40} {c.condition:4} {c.iterations:5} {c.settled:7} {c.all_succeed:11}  {costs}"
        )
    if not found:
        print("no condition ran its full phases")
        return
    settled = Counter(c.settled for c in found)
    print(f"\n{len(found)} conditions; settled at iteration: {dict(sorted(settled.items()))}")
    for phases in range(2, max(c.iterations for c in found) + 1):
        early = sum(c.settled >= phases for c in found)
        print(
            f"  {phases} phases: {early} stopped before settling, "
            f"{5 * sum(max(0, c.iterations - phases) for c in found)} sample rollouts saved"
        )


if __name__ == "__main__":
    run(main)
