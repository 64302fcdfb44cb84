"""Per-seed table and spread plot of evaluated streams, to judge a change by its worst seeds.

    python scripts/research/seed_table.py SWEEP_OR_RUN ... [--stage train2] [--label NAME ...]
                                          [--plot FILE.png]

Each argument is a sweep folder (every evaluated run folder in it) or a run folder; runs are
grouped by arm (the URDF's file name) and by argument (``--label`` names the arguments, e.g.
``before after``). Per run, from summary.json and eval.json (``scripts/evaluate.py``): the
training positions the final policy reaches, each test area's success after ``--stage``, the
worst of areas 0-4, the average final success over all areas, the forgetting, the rollouts of
local learning, the S-step rounds after the first fit, the largest final distance at any test
position after the last stage and after any stage (the policies of train0 and train1 are
tested at every area too), the largest joint speed over the joint's velocity limit after the
last stage and at any stage (evaluations made before the speed was recorded show '-'), the
test rollouts the arm's controller stopped at a limit over every stage, and the rollouts of
local learning it stopped (faults; runs made before faults were counted show 0). Then per arm and label: the
mean and the worst over seeds, and how many seeds have every area 0-4 at 90 % or more.
``--plot`` draws each seed's average final success and worst area 0-4, per arm and label.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from collections import defaultdict
from pathlib import Path
from typing import NamedTuple

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import evaluated_runs
from lolgps_torch.errors import LolgpsError


class SeedRow(NamedTuple):
    """One evaluated run's figures (see the module docstring)."""

    arm: str
    seed: int
    positions: str
    areas: list[float]
    worst_area: float
    average: float
    forgetting: float
    rollouts: int
    rounds: int
    worst_distance: float
    any_stage_distance: float
    peak_speed: float
    any_stage_speed: float
    eval_faults: int
    stream_faults: int


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", help="sweep or run folders")
    parser.add_argument("--stage", default="train2", help="stage of the areas (%(default)s)")
    parser.add_argument("--label", nargs="+", default=None, help="a name per folder")
    parser.add_argument("--plot", default=None, help="PNG of the per-seed spread")
    args = parser.parse_args()
    if args.label is not None and len(args.label) != len(args.folders):
        raise LolgpsError(f"--label needs {len(args.folders)} names, got {len(args.label)}")
    return args


def seed_row(folder: Path, stage: str) -> SeedRow:
    """The figures of one evaluated run folder."""
    try:
        config = json.loads((folder / "config.json").read_text())
        summary = json.loads((folder / "summary.json").read_text())["conditions"]
        evaluation = json.loads((folder / "eval.json").read_text())
        stages = {s["name"]: s for s in evaluation["stages"]}
        success = stages[stage]["per_position"]["success"]
        last = evaluation["stages"][-1]["per_position"]
    except (OSError, ValueError, KeyError) as error:
        raise LolgpsError(f"{folder}: not a finished, evaluated run ({error})") from None
    areas = [100.0 * sum(a) / len(a) for a in success]
    speeds = last.get("peak_speed")
    metrics = evaluation["metrics"]
    return SeedRow(
        arm=Path(config["task"]["urdf"]).stem,
        seed=int(config["stream"]["seed"]),
        positions=f"{sum(bool(c['policy_success_end']) for c in summary)}/{len(summary)}",
        areas=areas,
        worst_area=min(areas[:5]),
        average=float(metrics["average_final_success"]),
        forgetting=float(metrics["forgetting"]["final_distance"]["mean"]),
        rollouts=sum(int(c["rollouts"]) for c in summary),
        rounds=sum(int(c.get("repairs", 0)) for c in summary),
        worst_distance=max(max(area) for area in last["final_distance"]),
        any_stage_distance=max(
            max(max(area) for area in s["per_position"]["final_distance"])
            for s in evaluation["stages"]
        ),
        peak_speed=max(max(area) for area in speeds) if speeds else math.nan,
        any_stage_speed=max(
            (
                max(max(a) for a in st["per_position"]["peak_speed"])
                for st in evaluation["stages"]
                if "peak_speed" in st["per_position"]
            ),
            default=math.nan,
        ),  # fmt: skip
        eval_faults=sum(int(st.get("faults", 0)) for st in evaluation["stages"]),
        stream_faults=sum(int(c.get("faults", 0)) for c in summary),
    )


def print_tables(groups: dict[tuple[str, str], list[SeedRow]]) -> None:
    """The per-seed rows, then the aggregate per arm and label."""
    print("| arm | label | seed | positions | areas 0-6 after the stage (%) | worst area 0-4 (%) | "
          "average final success | forgetting (m) | rollouts | S-step rounds | worst final "
          "distance (m) | at any stage (m) | peak speed / limit | at any stage | faults in "
          "evaluation | faults in learning |")  # fmt: skip
    print("|---" * 16 + "|")
    for (arm, label), rows in groups.items():
        for r in rows:
            speed, anywhere = ("-" if math.isnan(v) else f"{v:.2f}"
                               for v in (r.peak_speed, r.any_stage_speed))  # fmt: skip
            print(
                f"| {arm} | {label} | {r.seed} | {r.positions} | "
                + " / ".join(f"{a:.0f}" for a in r.areas)
                + f" | {r.worst_area:.0f} | {r.average:.2f} | {r.forgetting:+.4f} | {r.rollouts} | "
                f"{r.rounds} | {r.worst_distance:.3f} | {r.any_stage_distance:.3f} | {speed} | "
                f"{anywhere} | {r.eval_faults} | {r.stream_faults} |"
            )
    print()
    print("| arm | label | seeds | all positions | areas 0-4 all >= 90 % | average final success: "
          "mean (worst) | worst area 0-4: mean (worst) | rollouts (mean) | S-step rounds (mean) | "
          "worst final distance (m) | at any stage (m) | peak speed / limit | faults in "
          "evaluation (all) | faults in learning (mean) |")  # fmt: skip
    print("|---" * 14 + "|")
    for (arm, label), rows in groups.items():
        full = sum(r.positions.split("/")[0] == r.positions.split("/")[1] for r in rows)
        good = sum(r.worst_area >= 90.0 for r in rows)
        avg = [r.average for r in rows]
        worst = [r.worst_area for r in rows]
        print(
            f"| {arm} | {label} | {len(rows)} | {full} | {good} | {statistics.mean(avg):.3f} "
            f"({min(avg):.2f}) | {statistics.mean(worst):.1f} ({min(worst):.0f}) | "
            f"{statistics.mean(r.rollouts for r in rows):.0f} | "
            f"{statistics.mean(r.rounds for r in rows):.1f} | "
            f"{max(r.worst_distance for r in rows):.3f} | "
            f"{max(r.any_stage_distance for r in rows):.3f} | "
            f"{max(r.any_stage_speed for r in rows):.2f} | {sum(r.eval_faults for r in rows)} | "
            f"{statistics.mean(r.stream_faults for r in rows):.1f} |"
        )


def plot(groups: dict[tuple[str, str], list[SeedRow]], path: str) -> None:
    """Each seed's average final success, worst area 0-4 and farthest test rollout, per arm
    and label."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 0.6 * len(groups) + 1.6), sharey=True)
    names = [f"{arm}, {label}" for arm, label in groups]
    for i, rows in enumerate(groups.values()):
        panels = (
            [r.average for r in rows],
            [r.worst_area / 100 for r in rows],
            [r.worst_distance for r in rows],
        )
        for ax, values in zip(axes, panels, strict=True):
            ax.scatter(values, [i] * len(values), alpha=0.6)
            ax.plot([statistics.mean(values)], [i], "k|", markersize=14)
    axes[0].set_yticks(range(len(names)), names)
    axes[0].set_xlabel("average final success, areas 0-6 (one dot per seed; bar: mean)")
    axes[1].set_xlabel("worst of areas 0-4 after the stage")
    axes[2].set_xlabel("farthest test rollout from its hole (m)")
    for ax in axes[:2]:
        ax.set_xlim(-0.02, 1.02)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    args = parse_args()
    labels = args.label or [Path(f).name for f in args.folders]
    groups: dict[tuple[str, str], list[SeedRow]] = defaultdict(list)
    for folder, label in zip(args.folders, labels, strict=True):
        for path in evaluated_runs(Path(folder)):
            row = seed_row(path, args.stage)
            groups[(row.arm, label)].append(row)
    ordered = {key: sorted(groups[key], key=lambda r: r.seed) for key in sorted(groups)}
    print_tables(ordered)
    if args.plot:
        plot(ordered, args.plot)


if __name__ == "__main__":
    run(main)
