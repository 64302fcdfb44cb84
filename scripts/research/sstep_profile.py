"""Where one stream S-step's time goes, rebuilt from a finished run (paper eq. 8).

    python scripts/research/sstep_profile.py --run DIR [--condition K] [--repeats 2]
        [--adam-dtype float32|float64] [--actions FILE] [--against FILE]

The S-step of condition ``K`` (default: the last) is rebuilt as the stream ran it: the replay
of conditions ``0 .. K-1`` (copied into a temporary replay file), condition ``K``'s D_g as the
new item labelled by its stored controllers, and the policy checkpointed after ``K - 1``, with
the run's S-step settings (``--adam-dtype`` in place of the run's loop type). It prints the rows, then the seconds (best of ``--repeats``, CPU
time of this process) of each part: reading the replay, the new D_g's perturbed copies, the
statistics and constant terms, the Adam loop (the whole call less those, with the rows' rewrite
into the net's units), and one closed-loop check (the policy's noiseless rollouts at the
``K + 1`` positions learnt so far). Last, the Adam loop's matrix products timed bare: for every
linear layer of the net (the gain head included), the forward product ``Z W^T`` and the
backward products ``G W`` (all but the first layer) and ``G^T Z``, on minibatch-sized operands
of the loop's type, repeated for the loop's steps. No arithmetic can make the loop cheaper than
its products at the machine's matrix-product speed, so the ratio says how much of the loop is
anything else.

``--actions FILE`` saves the policy the S-step call leaves, as its action means at the D_g
states of conditions ``0 .. K``; ``--against FILE`` prints the largest difference from such a
file, for instance one written by another checkout's code:

    PYTHONPATH=OTHER python scripts/research/sstep_profile.py --run DIR --actions other.pt
    python scripts/research/sstep_profile.py --run DIR --against other.pt
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any, get_args

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels
from lolgps_torch.lolgps.probes import policy_distances
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import GaussianPolicy
from lolgps_torch.policy.net import AdamDtype
from lolgps_torch.policy.sstep import _row_constants, set_statistics
from lolgps_torch.types import DistillBatch


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="finished run folder")
    parser.add_argument("--condition", type=int, default=None, help="(default: the last)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument(
        "--adam-dtype", choices=get_args(AdamDtype), default=None, help="(default: the run's)"
    )
    parser.add_argument("--actions", default=None, help="save the fitted policy's actions here")
    parser.add_argument("--against", default=None, help="compare them with this saved file")
    return parser.parse_args()


def best_seconds(body: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """The smallest process CPU time of ``repeats`` calls of ``body``, and its last result."""
    best, result = float("inf"), None
    for _ in range(repeats):
        start = time.process_time()
        result = body()
        best = min(best, time.process_time() - start)
    return best, result


def product_seconds(policy: GaussianPolicy, rows: int, steps: int, dtype: torch.dtype) -> float:
    """Process CPU seconds of ``steps`` rounds of the net's forward and backward matrix
    products on ``rows`` rows (see the module docstring), operands drawn at random."""
    layers = [m for m in policy.net if isinstance(m, torch.nn.Linear)]
    if policy.config.feedback:
        layers.append(policy.gain)
    products = []
    for i, layer in enumerate(layers):
        out, into = layer.weight.shape
        z, g = torch.randn(rows, into, dtype=dtype), torch.randn(rows, out, dtype=dtype)
        w = torch.randn(out, into, dtype=dtype)
        products += [(z, w.T), (g.T, z)] + ([(g, w)] if i > 0 else [])
    start = time.process_time()
    for _ in range(steps):
        for a, b in products:
            torch.mm(a, b)
    return time.process_time() - start


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    k = args.condition if args.condition is not None else loaded.records[-1].condition
    if not 0 <= k < len(loaded.records):
        raise LolgpsError(f"--condition {k}: the run has conditions 0 .. {len(loaded.records) - 1}")
    record = loaded.records[k]
    if record.p_cur is None:
        raise LolgpsError(f"condition {k} was labelled by the policy: no controller to augment")
    stream = loaded.info.stream
    task = loaded.make_task()
    policy: GaussianPolicy = (
        loaded.policy(k - 1)
        if k > 0
        else GaussianPolicy(task.layout.dX, task.layout.dU, loaded.policy(0).config)
    )
    config = policy.config
    if args.adam_dtype is not None:
        config = replace(config, adam_dtype=args.adam_dtype)
    labels = Labels(record.p_cur, record.p_pre, record.iterations)
    item = Labelled(record.offset, record.samples, labels)
    with tempfile.TemporaryDirectory() as tmp:
        replay = ReplayBuffer(RunFolder(tmp).replay_path)
        for r in loaded.records[:k]:
            replay.append_condition(
                r.condition, r.offset, r.samples, r.iterations, r.p_cur, r.p_pre
            )
        distiller = Distiller(task, config, stream.augment, stream.augment_scale, replay)
        gen = torch.Generator().manual_seed(0)
        t_read, stored = best_seconds(
            lambda: [replay.read_condition(i).samples.to_batch() for i in replay.conditions()],
            args.repeats,
        )
        t_aug, aug = best_seconds(lambda: distiller._augmented(item, gen), args.repeats)
        batch = DistillBatch(
            *(torch.cat(f) for f in zip(*stored, record.samples.to_batch(), aug, strict=True))
        )

        def statistics() -> None:
            set_statistics(policy, batch, config.pre_weight)
            with torch.no_grad():
                _row_constants(policy.covariance(), batch, config.pre_weight)

        t_stats, _ = best_seconds(statistics, args.repeats)
        state = {n: v.clone() for n, v in policy.state_dict().items()}

        def call() -> (
            None
        ):  # a fresh Distiller, so the call reads the replay as a stream's first does
            policy.load_state_dict(state)
            policy.trained = True
            Distiller(task, config, stream.augment, stream.augment_scale, replay)(policy, [item], 0)

        t_all, _ = best_seconds(call, args.repeats)
        with torch.no_grad():
            actions = policy(
                torch.cat([r.samples.x.flatten(0, 1) for r in loaded.records[: k + 1]])
            )
        offsets = [r.offset for r in loaded.records[: k + 1]]
        t_check, _ = best_seconds(lambda: policy_distances(task, policy, offsets), args.repeats)
    task.close()
    dtype = getattr(torch, config.adam_dtype)
    t_products, _ = best_seconds(
        lambda: product_seconds(policy, config.batch_size, config.steps, dtype), args.repeats
    )
    adam = t_all - t_read - t_aug - t_stats
    print(
        f"condition {k}: {batch.M} rows ({record.samples.x.shape[0]} new successes, "
        f"{sum(b.M for b in stored)} replay rows, {aug.M} perturbed rows); "
        f"{config.steps} Adam steps of {config.batch_size}"
    )
    print(
        f"CPU seconds: S-step call {t_all:.2f} = replay read {t_read:.2f} + perturbed copies "
        f"{t_aug:.2f} + statistics {t_stats:.2f} + Adam loop {adam:.2f}; "
        f"one closed-loop check at {len(offsets)} positions {t_check:.2f}"
    )
    print(
        f"the Adam loop's matrix products alone ({config.adam_dtype}): {t_products:.2f} "
        f"({t_products / adam:.2f} of the loop)"
    )
    if args.actions is not None:
        torch.save(actions, args.actions)
    if args.against is not None:
        other = torch.load(args.against)
        if other.shape != actions.shape:
            raise LolgpsError(
                f"{args.against}: actions {tuple(other.shape)}, not {tuple(actions.shape)}"
            )
        gap = (actions - other).abs()
        print(
            f"actions against {args.against}: largest difference {float(gap.max()):.3g} "
            f"(largest action {float(actions.abs().max()):.3g})"
        )


if __name__ == "__main__":
    run(main)
