"""Re-run a finished stream's S-steps, in stream order, with other S-step settings.

    python scripts/research/restream.py --run DIR [--steps N] [--batch-size B] [--lr LR]
                                        [--adam-dtype float32] [--repairs R] [--seed S]
                                        [--onpolicy] [--onpolicy-rounds R] [--onpolicy-noisy N]
                                        [--onpolicy-gate G] [--jitter MM] [--areas]
                                        [--augment N] [--augment-scale S]

Local learning is not repeated: condition ``k``'s D_g (its stored samples and controllers)
is distilled into the policy of the S-step of ``k - 1`` with the replay of ``0 .. k-1``, as
the stream does (:class:`CheckedSStep`: the S-step with its perturbed copies and replay, the
closed-loop check at the positions learnt so far, ``--onpolicy-rounds`` rounds on the states
the policy visits and up to ``--repairs`` while it misses). The labels' p_pre are those the
original stream's policy gave. Prints, per condition, the positions the
policy reaches after its S-step, the repair rounds and the CPU seconds of the checked S-step;
then the final policy's distances at every position and its fit on D_g in teacher standard
deviations (the ``fit`` of ``precision.py``, a script removed after commit 9d82b2d), its slope fit (the error of its
derivative along :func:`state_directions` against p_cur's ``K_t v``, in the same units, per
window of ten steps) and the positions it reaches with the hole moved by ``--jitter`` mm along
+x, -x, +y and -y (and, with ``--areas``, its success in each test area of
``scripts/evaluate.py``, noiseless), so S-step settings are compared on the same data in a minute rather than
re-running streams. With the run's own S-step settings and seed (the default seed) it runs the
run's S-steps on the same data, but not always to the same bits: the stream's visits were rolled
out in other batches (on its rollout workers), and the closed loop with contact can take another
course from a difference in the last bit (of the 12 KUKA streams of ba5b4c9, seeds 0, 2, 4, 5
and 6 re-ran to the run's own test areas, seeds 1, 3 and 11 did not).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace

import torch
from torch import Tensor

from lolgps_torch.cli import run
from lolgps_torch.data import ConditionRecord, ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, sample_area_positions
from lolgps_torch.evaluation.retention import fit_by_window
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels, consistent_states
from lolgps_torch.lolgps.probes import policy_distances
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.lolgps.stream import StreamConfig, checked_sstep, condition_seed
from lolgps_torch.policy import GaussianPolicy
from lolgps_torch.policy.net import AdamDtype
from lolgps_torch.task import PegTask

DIRECTION_STEP = 1e-3  # central-difference step of state_directions, in spreads


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
        "--onpolicy", action=argparse.BooleanOptionalAction, default=d.onpolicy,
        help="label the states the policy visits (%(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--onpolicy-rounds", type=int, default=d.onpolicy_rounds, help="(%(default)s)"
    )
    parser.add_argument(
        "--onpolicy-noisy", type=int, default=d.onpolicy_noisy, help="(%(default)s)"
    )
    parser.add_argument(
        "--onpolicy-gate", type=float, default=d.onpolicy_gate, help="(%(default)s)"
    )
    parser.add_argument("--jitter", type=float, default=4.0, help="mm (%(default)s)")
    parser.add_argument("--areas", action="store_true", help="test the final policy's areas")
    parser.add_argument("--augment", type=int, default=None, help="(default: the run's)")
    parser.add_argument("--augment-scale", type=float, default=None, help="(default: the run's)")
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        help="seed of the net and the S-steps (default: the run's)",
    )
    args = parser.parse_args()
    if min(args.steps, args.batch_size) < 1 or min(args.repairs, args.onpolicy_rounds) < 0:
        raise LolgpsError("--steps and --batch-size must be positive, the rounds >= 0")
    return args


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    run = loaded.info.stream
    seed = run.seed if args.seed is None else args.seed
    stream = StreamConfig(
        augment=run.augment if args.augment is None else args.augment,
        augment_scale=run.augment_scale if args.augment_scale is None else args.augment_scale,
        seed=seed,
        repairs=args.repairs,
        onpolicy=args.onpolicy,
        onpolicy_rounds=args.onpolicy_rounds,
        onpolicy_noisy=args.onpolicy_noisy,
        onpolicy_gate=args.onpolicy_gate,
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
            sstep = checked_sstep(task, stream, distill)
            for k, record in enumerate(loaded.records):
                if record.p_cur is None:
                    raise LolgpsError(f"condition {k} was labelled by the policy: not supported")
                labels = Labels(record.p_cur, record.p_pre, record.iterations)
                item = Labelled(record.offset, record.samples, labels)
                start = time.process_time()
                checked = sstep(policy, item, condition_seed(stream, k))
                seconds = time.process_time() - start
                total += seconds
                reached = sum(d < threshold for d in checked.distances)
                print(
                    f"condition {k}: reaches {reached}/{k + 1} after {checked.rounds} more "
                    f"rounds, {seconds:.1f} CPU s"
                )
                replay.append_condition(
                    k,
                    record.offset,
                    record.samples,
                    record.iterations,
                    record.p_cur,
                    record.p_pre,
                    checked.visited,
                )
        final = policy_distances(task, policy, offsets)
        j = args.jitter / 1000.0
        moved = [(x + a, y + b) for x, y in offsets for a, b in ((j, 0), (-j, 0), (0, j), (0, -j))]
        jittered = policy_distances(task, policy, moved)
        slope = slope_by_window(task, policy, loaded.records)
        if args.areas:
            areas = sample_area_positions(AreaConfig())
            rates = []
            for group in areas:
                d = policy_distances(task, policy, [(float(a), float(b)) for a, b in group])
                rates.append(sum(v < threshold for v in d) / len(d))
            print("areas: " + " / ".join(f"{100 * r:.0f}" for r in rates)
                  + f" %, average {sum(rates) / len(rates):.3f}")  # fmt: skip
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
    print(
        f"slope fit {sum(slope) / len(slope):.2f} teacher sd (per 10 steps: "
        + " ".join(f"{v:.1f}" for v in slope)
        + f"); hole moved {args.jitter:g} mm: reaches "
        + f"{sum(d < threshold for d in jittered)}/{len(jittered)}"
    )


def state_directions(task: PegTask, x: Tensor) -> Tensor:
    """Kinematically consistent state directions at D_g's states ``x: [M, T, dX]``: q and
    q-dot moved along ``spread * n``, ``n ~ N(0, I)`` drawn from a fixed seed, with ``spread``
    the per-step spread of the M samples, and the points and point velocities following to
    first order (central differences of :func:`consistent_states`)."""
    spread = (x - x.mean(0)).std(0, correction=0)
    gen = torch.Generator().manual_seed(0)
    step = DIRECTION_STEP * spread * torch.randn(x.shape, generator=gen, dtype=x.dtype).to(x)
    ahead = consistent_states(task, x + step, (0.0, 0.0))
    behind = consistent_states(task, x - step, (0.0, 0.0))
    return (ahead - behind) / (2.0 * DIRECTION_STEP)


def slope_by_window(
    task: PegTask, policy: GaussianPolicy, records: list[ConditionRecord]
) -> list[float]:
    """``sqrt(r^T P_cur r)``, ``r = J(x) v - K_t v`` for the policy's Jacobian ``J`` along
    :func:`state_directions` ``v`` at every stored state, averaged per window of ten steps."""
    errors = []
    for record in records:
        x, p = record.samples.x, record.p_cur
        if x.shape[0] == 0 or p is None:
            continue
        v = state_directions(task, x)
        derivative = torch.func.jvp(policy, (x,), (v,))[1]
        r = (derivative - (p.K @ v.unsqueeze(-1)).squeeze(-1)).unsqueeze(-1)
        errors.append((r.mT @ record.samples.prec_cur @ r).flatten(-3).sqrt())
    return [float(w.mean()) for w in torch.cat(errors).mean(0).split(10)]


if __name__ == "__main__":
    run(main)
