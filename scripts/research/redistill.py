"""Re-run the S-step on a finished run's replay with other settings, and test the result.

    python scripts/research/redistill.py --run DIR [--steps N] [--width W] [--batch-size B]
                                         [--lr LR] [--pre-weight W] [--jitter 0.004]
                                         [--seed S] [--no-feedback] [--out DIR2]

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
import time
from dataclasses import replace

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import save_policy
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.retention import fit_by_window
from lolgps_torch.lolgps.run import LoadedRun, load_run
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, distill, policy_actor


def parse_args() -> argparse.Namespace:
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
    parser.add_argument(
        "--no-feedback", dest="feedback", action="store_false", help="the plain MLP head"
    )
    parser.add_argument("--out", default=None, help="folder to save the policy in")
    args = parser.parse_args()
    if args.steps < 1 or args.width < 1 or args.layers < 1 or args.batch_size < 1:
        raise LolgpsError("--steps, --width, --layers and --batch-size must be positive")
    if args.pre_weight is not None and args.pre_weight < 0.0:
        raise LolgpsError(f"--pre-weight {args.pre_weight}: must be >= 0")
    return args


def policy_config(args: argparse.Namespace, loaded: LoadedRun) -> PolicyConfig:
    """The S-step settings of the flags, with the run's own p_pre weight by default."""
    run_weight = loaded.info.stream.policy.pre_weight
    return replace(
        PolicyConfig(),
        pre_weight=run_weight if args.pre_weight is None else args.pre_weight,
        hidden_sizes=(args.width,) * args.layers,
        steps=args.steps,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        seed=args.seed,
        feedback=args.feedback,
    )


def test_around(loaded: LoadedRun, policy: GaussianPolicy, jitter: float) -> None:
    """Print the policy's noiseless results at each training position and around it."""
    records = loaded.records
    around = [(0.0, 0.0), (jitter, 0.0), (-jitter, 0.0), (0.0, jitter), (0.0, -jitter)]
    offsets = [(r.offset[0] + dx, r.offset[1] + dy) for r in records for dx, dy in around]
    task = loaded.make_task()
    try:
        result = task.sample(policy_actor(policy, task.model), offsets)
    finally:
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


def main() -> None:
    args = parse_args()
    torch.manual_seed(args.seed)
    loaded = load_run(args.run)
    config = policy_config(args, loaded)
    batch = loaded.replay.load()
    if batch.M == 0:
        raise LolgpsError(f"{loaded.folder.replay_path} holds no successful samples")
    dX, dU = batch.x.shape[-1], batch.mean_cur.shape[-1]
    policy = GaussianPolicy(dX, dU, config)
    start = time.perf_counter()
    losses = distill(policy, batch, config)
    seconds = time.perf_counter() - start
    tail = losses[-min(100, len(losses)) :]
    print(
        f"fitted {batch.M} rows in {seconds:.1f}s; loss {losses[0]:.1f} -> "
        f"{sum(tail) / len(tail):.1f} (mean of the last {len(tail)} steps)"
    )
    fit = " ".join(f"{v:.1f}" for v in fit_by_window(policy, loaded))
    print(f"fit on D_g in teacher standard deviations, per 10 steps: {fit}")
    if args.out:
        save_policy(args.out, policy)
    test_around(loaded, policy, args.jitter)


if __name__ == "__main__":
    run(main)
