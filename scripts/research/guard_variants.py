"""Evaluate finished runs again under other guard settings, to see what the guard costs and saves.

    python scripts/research/guard_variants.py SWEEP_OR_RUN ... --out DIR [--speed V]
                                              [--torque T | --no-torque]
                                              [--retreat M | --no-retreat] [--off] [--workers N]

Each evaluated run folder (a sweep folder stands for every evaluated run in it) is copied to
``DIR/<run name>`` without its replay, its stage checkpoints' guards re-set, and evaluated on
the default test areas (``scripts/evaluate.py``). The guard's bounds are margins times what
D_g held (:mod:`lolgps_torch.policy.guard`); the run's config.json gives the margins it was
trained with, so the new ones are set as ratios: ``--speed V`` trips the brake at V times
D_g's largest joint speeds, ``--torque T`` bounds torques at T times the largest teacher
torque, ``--no-torque`` leaves them unbounded, ``--retreat M`` trips the brake once the tip
has moved M more away from its target, since the nearest it came, than any rollout of D_g
did (read from the run's replay), ``--no-retreat`` never, ``--off`` turns the whole guard
off. The brake gain stays the run's. The policies themselves are the runs' own, so only acting
changes; compare with ``scripts/research/seed_table.py RUNS DIR --label trained variant``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

import torch
from torch import Tensor

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import load_policy, save_policy
from lolgps_torch.data.replay import ReplayBuffer
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import evaluate_run
from lolgps_torch.policy.guard import Guard, tip_distance
from lolgps_torch.state import StateLayout


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", help="evaluated run folders or sweep folders")
    parser.add_argument("--out", required=True, help="folder of the re-guarded copies")
    parser.add_argument("--speed", type=float, default=None, help="brake trip, in D_g speeds")
    torque = parser.add_mutually_exclusive_group()
    torque.add_argument("--torque", type=float, default=None, help="bound, in teacher torques")
    torque.add_argument("--no-torque", action="store_true", help="torques unbounded")
    retreat = parser.add_mutually_exclusive_group()
    retreat.add_argument("--retreat", type=float, default=None, help="retreat trip margin (m)")
    retreat.add_argument("--no-retreat", action="store_true", help="no retreat trip")
    parser.add_argument("--off", action="store_true", help="no guard at all")
    parser.add_argument("--workers", type=int, default=2, help="evaluation processes")
    args = parser.parse_args()
    for name in ("speed", "torque", "retreat"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise LolgpsError(f"--{name} must be a number >= 0, got {value}")
    if args.workers < 1:
        raise LolgpsError(f"--workers must be at least 1, got {args.workers}")
    return args


def evaluated_runs(folder: Path) -> list[Path]:
    """``folder`` if it is an evaluated run, else its evaluated run subfolders."""
    if (folder / "eval.json").is_file():
        return [folder]
    found = sorted(p.parent for p in folder.glob("*/eval.json"))
    if not found:
        raise LolgpsError(f"{folder}: no evaluated run (eval.json) in it")
    return found


def largest_retreat(replay: ReplayBuffer, last: int, dU: int) -> Tensor:
    """The largest ``d_t - min_{s<=t} d_s`` over the D_g of conditions 0..``last``."""
    layout = StateLayout(dU)
    largest = torch.zeros((), dtype=torch.float64)
    for index in range(last + 1):
        samples = replay.read_condition(index).samples
        if samples.final_state is None or samples.x.shape[0] == 0:
            continue
        d = tip_distance(torch.cat([samples.x, samples.final_state[:, None]], 1), layout)
        largest = torch.maximum(largest, (d - d.cummin(1).values).amax())
    return largest


def reguarded(
    guard: Guard, trained: dict[str, float], args: argparse.Namespace, retreat: Tensor | None
) -> Guard:
    """``guard`` with the margins ``args`` asks for, its bounds rescaled from the ``trained``
    margins (``guard_speed``, ``guard_torque`` of the run's policy config); ``retreat``: D_g's
    largest retreat (:func:`largest_retreat`), when ``--retreat`` is given."""
    if args.off:
        return Guard.off(guard.torque.shape[0], guard.torque.device)
    speed = guard.speed * (args.speed / trained["guard_speed"]) if args.speed else guard.speed
    if args.no_torque:
        torque = guard.torque * math.inf
    elif args.torque:
        if trained["guard_torque"] is None:
            raise LolgpsError("--torque: the runs were trained without a torque bound")
        torque = guard.torque * (args.torque / trained["guard_torque"])
    else:
        torque = guard.torque
    if args.no_retreat:
        bound = guard.retreat.new_tensor(math.inf)
    elif retreat is not None:
        bound = retreat + args.retreat
    else:
        bound = guard.retreat
    return Guard(torque, speed, guard.brake, bound)


def copy_reguarded(source: Path, target: Path, args: argparse.Namespace) -> None:
    """The run ``source`` copied to ``target`` (no replay, no evaluation), guards re-set."""
    trained = json.loads((source / "config.json").read_text())["stream"]["policy"]
    if not trained.get("guard", False):
        raise LolgpsError(f"{source}: its policies were trained without a guard")
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(
        source, target, ignore=shutil.ignore_patterns("replay.h5", "eval.json", "*.png")
    )
    replay = ReplayBuffer(source / "replay.h5")
    for checkpoint in sorted((target / "checkpoints").iterdir()):
        policy = load_policy(checkpoint)
        last = int(checkpoint.name.rsplit("_", 1)[1])  # after_condition_NNN
        retreat = None if args.retreat is None else largest_retreat(replay, last, policy.dU)
        policy.set_guard(reguarded(policy.guard, trained, args, retreat))
        save_policy(checkpoint, policy)


def main() -> None:
    args = parse_args()
    sources = [r for folder in args.folders for r in evaluated_runs(Path(folder))]
    out = Path(args.out)
    for source in sources:
        target = out / source.name
        copy_reguarded(source, target, args)
        evaluation = evaluate_run(target, args.workers)  # writes target/eval.json
        print(
            f"{target}: average final success {evaluation['metrics']['average_final_success']:.3f}"
        )


if __name__ == "__main__":
    run(main)
