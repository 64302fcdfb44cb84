"""Re-run a finished stream's S-steps, in stream order, with other S-step settings.

    python scripts/research/restream.py --run DIR [--steps N] [--batch-size B] [--lr LR]
                                        [--adam-dtype float32] [--repairs R] [--seed S]
                                        [--repair-visits N]

Local learning is not repeated: condition ``k``'s D_g (its stored samples and controllers)
is distilled into the policy of the S-step of ``k - 1`` with the replay of ``0 .. k-1``, as
the stream does (:class:`CheckedSStep`: the S-step with its perturbed copies and replay, the
closed-loop check at the positions learnt so far, ``--repairs`` repair rounds). The labels'
p_pre are those the original stream's policy gave. Prints, per condition, the positions the
policy reaches after its S-step, the repair rounds and the CPU seconds of the checked S-step;
then the final policy's distances at every position and its fit on D_g in teacher standard
deviations (``scripts/research/precision.py``'s ``fit``), so S-step settings are compared on
the same data in a minute rather than re-running streams. With the run's own S-step settings
and seed (the default seed) it repeats the run's S-steps exactly.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.retention import fit_by_window
from lolgps_torch.lolgps.distillation import CheckedSStep, Distiller, Labelled, Labels
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.lolgps.stream import StreamConfig, condition_seed, policy_distances, visits
from lolgps_torch.policy import GaussianPolicy
from lolgps_torch.policy.net import AdamDtype


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    d = StreamConfig()
    parser.add_argument("--run", required=True, help="finished run folder")
    parser.add_argument("--steps", type=int, default=d.policy.steps, help="(%(default)s)")
    parser.add_argument("--batch-size", type=int, default=d.policy.batch_size)
    parser.add_argument("--lr", type=float, default=d.policy.learning_rate)
    parser.add_argument("--adam-dtype", choices=("float32", "float64"), default=d.policy.adam_dtype)
    parser.add_argument("--repairs", type=int, default=d.repairs, help="(%(default)s)")
    parser.add_argument(
        "--repair-visits", type=int, default=d.repair_visits, help="DAgger rollouts (%(default)s)"
    )
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        help="seed of the net and the S-steps (default: the run's)",
    )
    args = parser.parse_args()
    if min(args.steps, args.batch_size) < 1 or args.repairs < 0:
        raise LolgpsError("--steps and --batch-size must be positive, --repairs >= 0")
    return args


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    run = loaded.info.stream
    seed = run.seed if args.seed is None else args.seed
    stream = StreamConfig(
        augment=run.augment,
        augment_scale=run.augment_scale,
        seed=seed,
        repair_visits=args.repair_visits,
    )
    adam_dtype: AdamDtype = args.adam_dtype
    config = replace(
        stream.policy,
        pre_weight=run.policy.pre_weight,
        steps=args.steps,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        adam_dtype=adam_dtype,
        seed=seed,
    )
    task = loaded.make_task()
    threshold = task.config.world.success_threshold
    policy = GaussianPolicy(task.layout.dX, task.layout.dU, config)
    offsets = [r.offset for r in loaded.records]
    total = 0.0
    try:
        with tempfile.TemporaryDirectory() as tmp:
            replay = ReplayBuffer(RunFolder(tmp).replay_path)
            distill = Distiller(task, config, stream.augment, stream.augment_scale, replay)
            sstep = CheckedSStep(
                distill,
                lambda p, o: policy_distances(task, p, o),
                threshold,
                args.repairs,
                visits(task, stream),
            )
            for k, record in enumerate(loaded.records):
                if record.p_cur is None:
                    raise LolgpsError(f"condition {k} was labelled by the policy: not supported")
                labels = Labels(record.p_cur, record.p_pre, record.iterations)
                item = Labelled(record.offset, record.samples, labels)
                start = time.process_time()
                checked = sstep(policy, item, offsets[: k + 1], condition_seed(stream, k))
                seconds = time.process_time() - start
                total += seconds
                reached = sum(d < threshold for d in checked.distances)
                print(
                    f"condition {k}: reaches {reached}/{k + 1} after {checked.rounds} repair "
                    f"rounds, {seconds:.1f} CPU s"
                )
                replay.append_condition(
                    k, record.offset, record.samples, record.iterations, record.p_cur, record.p_pre
                )
        final = policy_distances(task, policy, offsets)
    finally:
        task.close()
    fit = fit_by_window(policy, loaded)
    print("final distances: " + " ".join(f"{d:.4f}" for d in final))
    print(
        f"final policy reaches {sum(d < threshold for d in final)}/{len(final)}; fit "
        f"{sum(fit) / len(fit):.2f} teacher sd (per 10 steps: "
        + " ".join(f"{v:.1f}" for v in fit)
        + f"); S-steps {total:.1f} CPU s"
    )


if __name__ == "__main__":
    run(main)
