"""Learn one hole position with the trajectory-centric loop (no global policy).

    python scripts/train_condition.py --urdf robots/kuka_peg.urdf --hole 0.0 0.0 --seed 0 --out runs/cond

Each iteration samples N rollouts, fits the dynamics and takes the KL-constrained C-step.
Per iteration it prints and appends to OUT/metrics.jsonl: mean cost, mean and best final
tip distance, success rate, epsilon, eta and the time spent sampling, fitting and solving.
"""

from __future__ import annotations

import argparse
import json
import os

import torch

from lolgps_torch.cli import add_task_arguments, run, task_config
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner
from lolgps_torch.sim.rollout import linear_gaussian_actor
from lolgps_torch.task import PegTask


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser)
    parser.add_argument(
        "--hole",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("DX", "DY"),
        help="hole offset (m) from the nominal position (default: 0 0)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--iterations", type=int, default=15, help="iteration limit (default 15)")
    parser.add_argument("--samples", type=int, default=5, help="rollouts per iteration (default 5)")
    parser.add_argument(
        "--stop-at-success",
        action="store_true",
        help="stop once at least 3 of 5 samples (60%%) succeed",
    )
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    torch.manual_seed(args.seed)
    config = LocalConfig(samples=args.samples)
    task = PegTask(task_config(args), n_worlds=args.samples, device=args.device)
    offset = (args.hole[0], args.hole[1])
    task.check_reachable(offset)
    os.makedirs(args.out, exist_ok=True)
    learner = LocalLearner(task, offset, config, seed=args.seed)
    metrics_path = os.path.join(args.out, "metrics.jsonl")
    with open(metrics_path, "w") as log:
        for i in range(args.iterations):
            it = learner.iteration()
            s = it.samples
            record = {
                "iteration": i,
                "mean_cost": float(s.cost.sum(1).mean()),
                "mean_distance": float(s.final_distance.mean()),
                "best_distance": float(s.final_distance.min()),
                "success_rate": float(s.success.double().mean()),
                "epsilon": it.epsilon,
                "eta": it.eta,
                "kl": it.kl,
                "step_mult": it.step_mult,
                "time_sample": it.time_sample,
                "time_fit": it.time_fit,
                "time_cstep": it.time_cstep,
            }
            log.write(json.dumps(record) + "\n")
            log.flush()
            print(
                f"iter {i:2d}  cost {record['mean_cost']:9.2f}  dist mean {record['mean_distance']:.3f} "
                f"best {record['best_distance']:.3f}  success {record['success_rate']:.0%}  "
                f"eps {it.epsilon:.1f} eta {it.eta:.3g}  "
                f"t {it.time_sample:.2f}/{it.time_fit:.2f}/{it.time_cstep:.2f} s",
                flush=True,
            )
            if args.stop_at_success and record["success_rate"] >= 0.6:
                break
    if not torch.isfinite(learner.p_cur.k).all():
        raise LolgpsError("the controller diverged (non-finite gains)")
    zero = torch.zeros(1, task.T, task.layout.dU, dtype=torch.float64)
    final = task.sample(linear_gaussian_actor(learner.p_cur, zero), [offset])
    summary = {
        "hole": list(offset),
        "seed": args.seed,
        "iterations": i + 1,
        "noiseless_final_distance": float(final.final_distance[0]),
    }
    with open(os.path.join(args.out, "summary.json"), "w") as fh:
        json.dump(summary, fh, indent=2)
    print(
        f"noiseless final distance of the last controller: {summary['noiseless_final_distance']:.4f} m"
    )
    task.close()


if __name__ == "__main__":
    run(main)
