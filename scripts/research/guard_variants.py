"""Evaluate finished runs again under other guard settings, to see what the guard costs and saves.

    python scripts/research/guard_variants.py SWEEP_OR_RUN ... --out DIR [--speed V]
                                              [--window W] [--retreat R] [--brake B]
                                              [--torque T | --no-torque] [--hover H TIME]
                                              [--off] [--workers N]

Each evaluated run folder (a sweep folder stands for every evaluated run in it) is copied to
``DIR/<run name>`` without its replay, its stage checkpoints' guards re-set, and evaluated on
the default test areas (``scripts/evaluate.py``). The guard's bounds are margins times what
D_g held (:mod:`lolgps_torch.policy.guard`); the run's config.json gives the margins it was
trained with, so the new ones are set as ratios: ``--speed V`` trips the brake at V times
D_g's largest joint speeds, ``--torque T`` bounds torques at T times the largest teacher
torque, ``--no-torque`` leaves them unbounded, ``--off`` turns the whole guard off.
``--window W`` fits the trip speeds step by step instead, to the run's replay (the D_g of the
conditions up to each checkpoint), at ``--speed`` times (default: the run's margin) D_g's
largest speed from W steps before each step on. ``--retreat R`` fits the retreat that trips the
brake to the replay as well, R metres beyond D_g's largest (a run trained before the retreat
trip has none); with either, ``--torque T`` is fitted to the replay too, T times the largest
teacher torque (a run trained without a bound has none to rescale). ``--brake B`` has the brake take B of the joint speeds away per control
step instead of the run's share (default: the run's). ``--hover H TIME`` has the brake steer the
peg to H m above the hole's mouth, with time constant TIME s, until the tip is within 2 cm of that
point, instead of stopping the arm where it is. The policies themselves are the runs' own, so
only acting (by this checkout's guard) changes; compare with
``scripts/research/seed_table.py RUNS DIR --label trained variant``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import load_policy, save_policy
from lolgps_torch.data.run_folder import EVAL_FILE, REPLAY_FILE, evaluated_runs
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import evaluate_run
from lolgps_torch.lolgps.distillation import guard_of
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import PolicyConfig
from lolgps_torch.policy.guard import Guard
from lolgps_torch.state import StateLayout
from lolgps_torch.types import ConditionSamples


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
    parser.add_argument("--window", type=int, default=None, help="per-step trip speeds")
    parser.add_argument("--retreat", type=float, default=None, help="retreat trip margin (m)")
    parser.add_argument("--brake", type=float, default=None, help="brake's share per step")
    parser.add_argument(
        "--hover",
        type=float,
        nargs=2,
        default=None,
        metavar=("H", "TIME"),
        help="the brake steers the peg H m above the hole's mouth, time constant TIME s",
    )
    parser.add_argument("--off", action="store_true", help="no guard at all")
    parser.add_argument("--workers", type=int, default=2, help="evaluation processes")
    args = parser.parse_args()
    for name in ("speed", "torque"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise LolgpsError(f"--{name} must be a positive number, got {value}")
    if args.brake is not None and not 0.0 < args.brake <= 1.0:
        raise LolgpsError(f"--brake must be in (0, 1], got {args.brake}")
    if args.retreat is not None and not 0.0 <= args.retreat < math.inf:
        raise LolgpsError(f"--retreat must be a distance >= 0 (m), got {args.retreat}")
    if args.window is not None and args.window < 0:
        raise LolgpsError(f"--window must be at least 0, got {args.window}")
    if args.workers < 1:
        raise LolgpsError(f"--workers must be at least 1, got {args.workers}")
    if args.hover is not None and not (0.0 <= args.hover[0] < math.inf and args.hover[1] > 0):
        raise LolgpsError(f"--hover needs a height >= 0 and a time > 0, got {args.hover}")
    return args


def reguarded(
    guard: Guard,
    trained: dict[str, float],
    args: argparse.Namespace,
    data: list[ConditionSamples],
    depth: float,
) -> Guard:
    """``guard`` with the margins ``args`` asks for, its bounds rescaled from the ``trained``
    margins (``guard_speed``, ``guard_torque`` of the run's policy config); with a window, its
    trip speeds fitted per step to the D_g ``data``; a hover point above the mouth of the
    run's hole, ``depth`` (m) deep."""
    if args.off:
        return Guard.off(guard.torque.shape[0], guard.torque.device)
    fitted = None
    if args.window is not None or args.retreat is not None:
        kept = trained.get("guard_window")  # the run's window where no new one is asked for
        window = args.window if args.window is not None else None if kept is None else int(kept)
        config = PolicyConfig(
            guard_speed=args.speed or trained["guard_speed"], guard_window=window,
            guard_retreat=args.retreat, guard_torque=args.torque,
        )  # fmt: skip
        unlimited = torch.full_like(guard.torque, math.inf)  # D_g's trip speeds alone
        fitted = guard_of(data, StateLayout(guard.torque.shape[0]), config, depth, unlimited)
        if fitted is None:
            raise LolgpsError("--window, --retreat: a checkpoint's conditions hold no rollout")
    if args.window is not None and fitted is not None:
        speed = fitted.speed
    elif args.speed:
        speed = guard.speed * (args.speed / trained["guard_speed"])
    else:
        speed = guard.speed
    retreat = guard.retreat if args.retreat is None or fitted is None else fitted.retreat
    torque = _torque(guard, trained, args, fitted)
    brake = guard.brake if args.brake is None else torch.tensor(args.brake).to(guard.brake)
    hover = guard.hover
    if args.hover is not None:
        hover = guard.hover.new_tensor([depth + args.hover[0], args.hover[1]])
    return Guard(torque, speed, brake, retreat, hover)


def _torque(
    guard: Guard, trained: dict[str, float], args: argparse.Namespace, fitted: Guard | None
) -> torch.Tensor:
    """The torque bound ``args`` asks for (:func:`reguarded`)."""
    if args.no_torque:
        return torch.full_like(guard.torque, math.inf)
    elif args.torque and fitted is not None:
        return fitted.torque
    elif args.torque:
        if trained["guard_torque"] is None:
            raise LolgpsError(
                "--torque: the runs were trained without a torque bound (add --window or "
                "--retreat to fit it to the replay)"
            )
        return guard.torque * (args.torque / trained["guard_torque"])
    else:
        return guard.torque


def copy_reguarded(source: Path, target: Path, args: argparse.Namespace) -> None:
    """The run ``source`` copied to ``target`` (no replay, no evaluation), guards re-set."""
    config = json.loads((source / "config.json").read_text())
    trained, depth = config["stream"]["policy"], config["task"]["world"]["depth"]
    if not trained.get("guard", False):
        raise LolgpsError(f"{source}: its policies were trained without a guard")
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source, target, ignore=shutil.ignore_patterns(REPLAY_FILE, EVAL_FILE, "*.png"))
    refit = args.window is not None or args.retreat is not None
    records = load_run(source).records if refit else []
    for checkpoint in sorted((target / "checkpoints").iterdir()):
        policy = load_policy(checkpoint)
        last = int(checkpoint.name.rsplit("_", 1)[-1]) if records else -1
        data = [r.samples for r in records if r.condition <= last]
        policy.set_guard(reguarded(policy.guard, trained, args, data, depth))
        save_policy(checkpoint, policy)
    print(f"{target}: the last policy's retreat trip rho {float(policy.guard.retreat):.4f} m")


def main() -> None:
    args = parse_args()
    sources = [r for folder in args.folders for r in evaluated_runs(folder)]
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
