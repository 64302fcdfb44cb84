"""Learn a stream of conditions with LOLGPS (paper Algorithm 2): the project's main command.

    python scripts/run_stream.py --urdf robots/kuka_peg.urdf

With no other flags it runs the paper's training stream in the default geometry: train0 = the
4 hole offsets (+-0.02, +-0.02) m around the nominal position, train1 = +2 seeded positions in
test area 2 (0.10 m along the table's lateral axis), train2 = +2 in area 4 (0.20 m).

It writes into --out: config.json, metrics.jsonl (one line per iteration, with phase times),
replay.h5 (the successful trajectories D_g of every condition), checkpoints/after_condition_XXX/
(the global policy after each condition) and summary.json, and prints a table at the end.
An interrupted run continues from its last completed condition with --resume.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict, replace
from typing import Any

import torch

from lolgps_torch.cli import add_task_arguments, run, task_config
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.lolgps.batch import BatchLearner
from lolgps_torch.lolgps.stream import StreamConfig, StreamLearner
from lolgps_torch.task import PegTask

METHODS = ("lolgps", "naive", "batch")


def parse_args() -> argparse.Namespace:
    d = StreamConfig()
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser, default_urdf="robots/kuka_peg.urdf")
    parser.add_argument(
        "--conditions",
        default=None,
        help="JSON file with a list of planar hole offsets [[dx, dy], ...] (m); "
        "default: the paper's train0/train1/train2 stream",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="lolgps",
        help="lolgps; naive sequential (no p_pre, no replay); or batch GPS (all "
        "conditions at once, an S-step every iteration; --resume restarts it) "
        "(default: lolgps)",
    )
    parser.add_argument(
        "--alpha",
        type=float,
        default=d.alpha,
        help=f"weight of p_pre in p_act = alpha p_pre + (1 - alpha) p_cur (default {d.alpha})",
    )
    parser.add_argument(
        "--alpha-schedule",
        choices=("constant", "dynamic"),
        default=d.alpha_schedule,
        help=f"dynamic: alpha += {d.alpha_step} per iteration (default {d.alpha_schedule})",
    )
    parser.add_argument(
        "--cstep-anchor",
        choices=("previous", "pre"),
        default=d.cstep_anchor,
        help="the C-step's KL anchor once a policy exists: the previous p_cur "
        f"(trust region) or p_pre (paper eq. 7) (default {d.cstep_anchor})",
    )
    parser.add_argument(
        "--pre-fit",
        choices=("gmm", "jacobian"),
        default=d.pre_fit,
        help="how p_pre linearises the policy: regression with a GMM prior, or the policy's "
        f"own Jacobian at the samples (default {d.pre_fit})",
    )
    parser.add_argument(
        "--plan-through-mixture",
        action=argparse.BooleanOptionalAction,
        default=d.plan_through_mixture,
        help="the C-step optimises the acting mixture p_act, not p_cur alone "
        f"(default {d.plan_through_mixture})",
    )
    parser.add_argument(
        "--samples",
        type=int,
        default=d.local.samples,
        help=f"rollouts per iteration (default {d.local.samples})",
    )
    parser.add_argument(
        "--max-iterations",
        type=int,
        default=d.max_iterations,
        help=f"iteration limit per condition (default {d.max_iterations})",
    )
    parser.add_argument(
        "--success-phases",
        type=int,
        default=d.success_phases,
        help=f"iterations with successful samples to collect (default {d.success_phases})",
    )
    parser.add_argument(
        "--distill-steps",
        type=int,
        default=d.policy.steps,
        help=f"Adam steps per S-step (default {d.policy.steps})",
    )
    parser.add_argument(
        "--pre-weight",
        type=float,
        default=d.policy.pre_weight,
        help="weight lambda of KL(pi || p_pre) in the S-step loss, KL(pi || p_cur) + "
        f"lambda KL(pi || p_pre) (paper eq. 8: 1; default {d.policy.pre_weight:g})",
    )
    parser.add_argument(
        "--corrections",
        type=int,
        default=d.corrections.rounds,
        help="policy-correction rounds per S-step: the policy's own states, labelled by the "
        f"local controllers (0: off) (default {d.corrections.rounds})",
    )
    parser.add_argument(
        "--consolidate",
        type=int,
        default=d.consolidate,
        help="MDGPS iterations after each condition's S-step, the C-step anchored to the "
        f"updated policy, each followed by a short S-step (default {d.consolidate})",
    )
    parser.add_argument(
        "--refits",
        type=int,
        default=d.refits,
        help="checked refits of each S-step while the policy misses a learnt condition, kept "
        "only when its noiseless rollouts there improve; also guards --consolidate "
        f"(default {d.refits})",
    )
    parser.add_argument(
        "--augment",
        type=int,
        default=d.augment,
        help=f"perturbed copies of each D_g state in the S-step (default {d.augment})",
    )
    parser.add_argument(
        "--augment-mode",
        choices=["independent", "kinematic"],
        default=d.augment_mode,
        help="perturb every state dimension on its own, or q and q-dot with the points and "
        "their velocities recomputed by kinematics (default %(default)s)",
    )
    parser.add_argument(
        "--no-replay", action="store_true", help="distil on the current condition only"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", default=None, help="output folder (default: runs/<method>-seed<S>)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue an interrupted run in --out"
    )
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    return parser.parse_args()


def stream_config(args: argparse.Namespace) -> StreamConfig:
    d = StreamConfig()
    naive = args.method == "naive"
    if args.pre_weight < 0.0:
        raise LolgpsError(f"--pre-weight {args.pre_weight}: must be >= 0")
    return StreamConfig(
        alpha=0.0 if naive else args.alpha,
        alpha_schedule=args.alpha_schedule,
        use_pre=not naive,
        pre_fit=args.pre_fit,
        plan_through_mixture=args.plan_through_mixture,
        cstep_anchor=args.cstep_anchor,
        replay=not (naive or args.no_replay),
        success_phases=args.success_phases,
        max_iterations=args.max_iterations,
        seed=args.seed,
        local=replace(d.local, samples=args.samples),
        augment=args.augment,
        augment_mode=args.augment_mode,
        consolidate=args.consolidate,
        refits=args.refits,
        policy=replace(
            d.policy, steps=args.distill_steps, seed=args.seed, pre_weight=args.pre_weight
        ),
        corrections=replace(d.corrections, rounds=args.corrections),
    )


def load_conditions(
    args: argparse.Namespace,
) -> tuple[list[tuple[float, float]], list[dict[str, Any]]]:
    if args.conditions is None:
        return default_training_stream(AreaConfig(), args.seed)
    try:
        with open(args.conditions) as fh:
            raw = json.load(fh)
        conditions = [(float(c[0]), float(c[1])) for c in raw]
    except (OSError, ValueError, TypeError, IndexError) as exc:
        raise LolgpsError(
            f"--conditions {args.conditions}: expected a JSON list of [dx, dy] ({exc})"
        ) from None
    if not conditions:
        raise LolgpsError(f"--conditions {args.conditions} is empty")
    return conditions, [{"name": "stream", "last_condition": len(conditions) - 1}]


def main() -> None:
    args = parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise LolgpsError(f"--device {args.device}: CUDA is not available here")
    out = args.out or os.path.join("runs", f"{args.method}-seed{args.seed}")
    conditions, stages = load_conditions(args)
    tcfg, scfg = task_config(args), stream_config(args)
    config = {
        "method": args.method,
        "seed": args.seed,
        "task": asdict(tcfg),
        "stream": asdict(scfg),
        "conditions": [list(c) for c in conditions],
        "stages": stages,
    }
    config = json.loads(json.dumps(config))  # tuples -> lists, as stored
    config_path = os.path.join(out, "config.json")
    if os.path.exists(config_path):
        if not args.resume:
            raise LolgpsError(
                f"{out} already holds a run; pass --resume to continue it, or another --out"
            )
        with open(config_path) as fh:
            saved = json.load(fh)
        if saved != config:
            raise LolgpsError(
                f"{out} holds a run with a different configuration; use another --out"
            )
    task = PegTask(tcfg, n_worlds=scfg.local.samples, device=args.device)
    for offset in conditions:
        task.check_reachable(offset)
    os.makedirs(out, exist_ok=True)
    with open(config_path, "w") as fh:
        json.dump(config, fh, indent=1)

    with open(os.path.join(out, "metrics.jsonl"), "a") as metrics:
        total = len(conditions)

        def log(record: dict[str, Any]) -> None:
            metrics.write(json.dumps(record) + "\n")
            metrics.flush()
            if record.get("event") == "distilled":
                print(f"S-step took {record['time_distill']:.1f}s", flush=True)
                return
            if record.get("event") == "refit":
                verdict = "kept" if record["kept"] else "undone"
                print(
                    f"condition {record['condition'] + 1}/{total}  refit {record['round'] + 1}: "
                    f"policy succeeds at {record['successes']}/{record['of']} learnt "
                    f"conditions, {verdict}",
                    flush=True,
                )
                return
            if record.get("event") == "consolidation undone":
                print(
                    f"condition {record['condition'] + 1}/{total}  consolidation round "
                    f"{record['round'] + 1} did not improve the policy: undone",
                    flush=True,
                )
                return
            print(
                f"condition {record['condition'] + 1}/{total}  iter {record['iteration']:2d}  "
                f"cost {record['mean_cost']:8.2f}  distance mean {record['mean_distance']:.3f} "
                f"best {record['best_distance']:.3f}  success {record['success_rate']:4.0%}  "
                f"[{record['time_sample']:.2f}s sample, {record['time_fit']:.2f}s fit, "
                f"{record['time_cstep']:.2f}s C-step]",
                flush=True,
            )

        def done(entry: dict[str, Any]) -> None:
            print(
                f"condition {entry['condition'] + 1}/{total} done: first success at iteration "
                f"{entry['first_success_iteration']}, p_cur distance {entry['local_final_distance']:.4f}, "
                f"global policy distance {entry['policy_final_distance_after']:.4f}",
                flush=True,
            )

        learner = (BatchLearner if args.method == "batch" else StreamLearner)(task, scfg, out, log)
        summary = learner.run(conditions, done)
    with open(os.path.join(out, "summary.json.tmp"), "w") as fh:
        json.dump({"method": args.method, "seed": args.seed, "conditions": summary}, fh, indent=1)
    os.replace(os.path.join(out, "summary.json.tmp"), os.path.join(out, "summary.json"))

    print(
        f"\n{'cond':>4} {'offset (m)':>17} {'iters':>5} {'1st ok':>6} {'p_cur':>8} "
        f"{'pi after':>9} {'pi end':>8}"
    )
    for e in summary:
        first = "-" if e["first_success_iteration"] is None else str(e["first_success_iteration"])
        print(
            f"{e['condition']:>4} ({e['offset'][0]:+.3f}, {e['offset'][1]:+.3f}) {e['iterations']:>5} "
            f"{first:>6} {e['local_final_distance']:8.4f} {e['policy_final_distance_after']:9.4f} "
            f"{e['policy_final_distance_end']:8.4f}"
        )
    solved = sum(e["policy_success_end"] for e in summary)
    print(
        f"global policy alone succeeds at {solved}/{len(summary)} training positions; results in {out}"
    )
    task.close()


if __name__ == "__main__":
    run(main)
