"""Why a run's global policy stops the arm: the reflex's own reason for each faulted test rollout.

    python scripts/research/limit_faults.py --run DIR [--stage NAME] [--groups K ...]
                                           [--per-group N]

The policy of the stage (default: the last) runs again, without noise, at the first N test
positions of each chosen group of DIR/eval.json (written by ``scripts/evaluate.py``), in the
plant the run was trained in, through this checkout's guard. For every rollout the reflex stopped, it prints the reflex's
line (which joint, velocity or position limit, at which control step) and the joint speeds
over their limits at the step before; then a count per group and kind (velocity or position
limit, joint). ``evaluate.py`` gives how many rollouts faulted; this gives why.
"""

from __future__ import annotations

import argparse
import re
from collections import Counter

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import read_evaluation
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import policy_actor


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="an evaluated run folder")
    parser.add_argument("--stage", help="a training stage's name (default: the last)")
    parser.add_argument("--groups", type=int, nargs="+", help="group indices (default: all)")
    parser.add_argument("--per-group", type=int, default=10, help="positions per group")
    return parser.parse_args()


def kind_of(reason: str) -> str:
    """``velocity joint J`` or ``position joint J`` from a reflex line."""
    joint = re.match(r"joint (\d+)", reason)
    limit = "velocity" if "velocity limit" in reason else "position"
    return f"{limit} joint {joint.group(1) if joint else '?'}"


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    evaluation = read_evaluation(args.run)
    stages = {s["name"]: s for s in evaluation["stages"]}
    if args.stage is not None and args.stage not in stages:
        raise LolgpsError(f"--stage {args.stage}: the run's stages are {sorted(stages)}")
    stage = stages[args.stage] if args.stage is not None else evaluation["stages"][-1]
    groups = evaluation["groups"]
    chosen = args.groups if args.groups is not None else list(range(len(groups)))
    policy = loaded.policy(stage["last_condition"])
    task = loaded.make_task(n_worlds=1)
    counts: Counter[tuple[str, str]] = Counter()
    try:
        velocity = task.model.velocity
        for k in chosen:
            name = groups[k]["label"]
            for position in groups[k]["positions"][: args.per_group]:
                rolled = task.sampler.rollout(policy_actor(policy, task.model), [tuple(position)])
                reason = task.sampler.worlds[0].fault
                if reason is None:
                    continue
                counts[(name, kind_of(reason))] += 1
                step = int(re.findall(r"step (\d+)", reason)[-1])
                speeds = rolled.x[0, max(step - 1, 0), task.layout.qd].abs() / velocity
                shown = " ".join(f"{float(v):.2f}" for v in speeds)
                print(f"{name} ({position[0]:+.3f}, {position[1]:+.3f}): {reason}; |q-dot|/v "
                      f"at step {max(step - 1, 0)}: {shown}")  # fmt: skip
    finally:
        task.close()
    print(f"stage {stage['name']}, {args.per_group} positions per group:")
    for (name, kind), n in sorted(counts.items()):
        print(f"  {name:10s} {kind:20s} {n}")
    if not counts:
        print("  no faults")


if __name__ == "__main__":
    run(main)
