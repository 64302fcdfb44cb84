"""Re-run the S-step on a finished run's replay with other settings, and test the result.

    python scripts/redistill.py --run DIR [--steps N] [--width W] [--batch-size B] [--lr LR]
                                [--pre-weight W] [--jitter 0.004] [--seed S] [--out DIR2]

A fresh global policy is fitted (paper eq. 8) on the D_g of every condition in DIR/replay.h5,
with the stored targets (and the run's weight on the p_pre term unless ``--pre-weight`` is
given), all at once: the batch S-step the stream's last distillation
approximates. It then runs without noise at each training position and at four positions
``--jitter`` metres away from it (+-x, +-y), and prints the final distances and success counts.
Local learning is not repeated, so S-step settings can be compared on the same data in seconds
rather than re-running the stream. ``--out`` saves the policy (policy.pt, policy.json).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import read_run
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, distill, policy_actor
from lolgps_torch.task import PegTask, task_config_from_dict
from lolgps_torch.types import DistillBatch


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    d = PolicyConfig()
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    parser.add_argument("--steps", type=int, default=d.steps, help="Adam steps (%(default)s)")
    parser.add_argument(
        "--width", type=int, default=d.hidden_sizes[0], help="units per hidden layer (%(default)s)"
    )
    parser.add_argument(
        "--layers", type=int, default=len(d.hidden_sizes), help="hidden layers (%(default)s)"
    )
    parser.add_argument("--batch-size", type=int, default=d.batch_size, help="(%(default)s)")
    parser.add_argument("--lr", type=float, default=d.learning_rate, help="(%(default)s)")
    parser.add_argument(
        "--pre-weight",
        type=float,
        default=None,
        help="weight of the KL(pi || p_pre) term, 0 drops it (default: the run's own)",
    )
    parser.add_argument(
        "--jitter", type=float, default=0.004, help="offset (m) of the extra test positions"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="folder to save the policy in")
    args = parser.parse_args()
    if args.steps < 1 or args.width < 1 or args.layers < 1 or args.batch_size < 1:
        raise LolgpsError("--steps, --width, --layers and --batch-size must be positive")
    if args.pre_weight is not None and args.pre_weight < 0.0:
        raise LolgpsError(f"--pre-weight {args.pre_weight}: must be >= 0")
    torch.manual_seed(args.seed)

    info = read_run(args.run)
    replay = ReplayBuffer(Path(args.run) / "replay.h5")
    indices = replay.conditions()
    if not indices:
        raise LolgpsError(f"{args.run}/replay.h5 holds no conditions")
    records = [replay.read_condition(i) for i in indices]
    batch = replay.load(indices)
    if batch.M == 0:
        raise LolgpsError(f"{args.run}/replay.h5 holds no successful samples")
    try:
        with open(Path(args.run) / "config.json") as fh:
            # runs made before the weight existed used the paper's equal weights
            run_weight = float(json.load(fh)["stream"]["policy"].get("pre_weight", 1.0))
    except (KeyError, TypeError, AttributeError, ValueError) as exc:
        raise LolgpsError(f"{args.run}/config.json: no stream.policy settings ({exc})") from None
    config = replace(
        d,
        pre_weight=run_weight if args.pre_weight is None else args.pre_weight,
        hidden_sizes=(args.width,) * args.layers,
        steps=args.steps,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        seed=args.seed,
    )
    task = PegTask(task_config_from_dict(info.task), n_worlds=5)
    policy = GaussianPolicy(task.layout.dX, task.layout.dU, config)
    start = time.perf_counter()
    losses = distill(policy, DistillBatch(*batch), config)
    seconds = time.perf_counter() - start
    tail = losses[-min(100, len(losses)) :]
    print(
        f"fitted {batch.M} rows in {seconds:.1f}s; loss {losses[0]:.1f} -> "
        f"{sum(tail) / len(tail):.1f} (mean of the last {len(tail)} steps)"
    )
    if args.out:
        policy.save(args.out)

    j = args.jitter
    around = [(0.0, 0.0), (j, 0.0), (-j, 0.0), (0.0, j), (0.0, -j)]
    offsets = [(r.offset[0] + dx, r.offset[1] + dy) for r in records for dx, dy in around]
    result = task.sample(policy_actor(policy), offsets)
    task.close()
    success = result.success.reshape(len(records), len(around))
    distance = result.final_distance.reshape(len(records), len(around))
    for record, s, dist in zip(records, success, distance, strict=True):
        print(
            f"condition {record.condition} ({record.offset[0]:+.3f}, {record.offset[1]:+.3f}): "
            f"distance {float(dist[0]):.4f}, jittered {int(s[1:].sum())}/{len(around) - 1}"
        )
    print(
        f"training positions {int(success[:, 0].sum())}/{len(records)}, "
        f"with jittered {int(success.sum())}/{success.numel()}"
    )


if __name__ == "__main__":
    run(main)
