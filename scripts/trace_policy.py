"""Trace a run's global policy step by step at its training positions, to see how it misses.

    python scripts/trace_policy.py --run DIR [--checkpoint N] [--steps 0 3 6 10 20 50 99]

For each condition in DIR/replay.h5 it prints two lines:

- ``rollout``: the tip's error ``p_tip - p*_tip`` (mm; x, y, z with z up) at the chosen steps of
  the policy's noiseless rollout there, and the final distance (m). A peg stopped on the plate
  beside the mouth of the 0.10 m deep hole shows as z near +100 mm with a lateral error.
- ``D_g fit``: at the same steps, the policy's action error on the condition's stored
  successful states, averaged over samples: relative, ``|mu_theta(x) - mu_cur(x)| / |mu_cur(x)|``,
  and in p_cur's standard deviations, ``sqrt(d^T P_cur d)`` with ``d = mu_theta(x) - mu_cur(x)``
  (the S-step's own measure), where ``mu_cur``, ``P_cur`` are the stored distillation targets.
  It tells an under-fitted S-step (large on D_g) from a policy that fits D_g but drifts off it.

``--checkpoint`` picks the policy saved after that condition (default: the last).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import checkpoint_dir, read_run
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.task import PegTask, task_config_from_dict


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    parser.add_argument("--checkpoint", type=int, default=None, help="policy after condition N")
    parser.add_argument(
        "--steps", type=int, nargs="+", default=[0, 3, 6, 10, 20, 50, 99], help="steps to print"
    )
    args = parser.parse_args()
    info = read_run(args.run)
    replay = ReplayBuffer(Path(args.run) / "replay.h5")
    records = [replay.read_condition(i) for i in replay.conditions()]
    if not records:
        raise LolgpsError(f"{args.run}/replay.h5 holds no conditions")
    last = records[-1].condition if args.checkpoint is None else args.checkpoint
    policy = GaussianPolicy.load(checkpoint_dir(args.run, last))
    task = PegTask(task_config_from_dict(info.task), n_worlds=5)
    bad = [t for t in args.steps if not 0 <= t < task.T]
    if bad:
        raise LolgpsError(f"--steps must lie in [0, {task.T}), got {bad}")
    steps = torch.tensor(args.steps)
    rollouts = task.sample(policy_actor(policy), [r.offset for r in records])
    task.close()
    tip = task.layout.points.start
    print(f"policy after condition {last}; columns: steps {args.steps}")
    for i, record in enumerate(records):
        error = rollouts.x[i, steps, tip : tip + 3] * 1000.0
        cells = " ".join(f"({e[0]:+.0f},{e[1]:+.0f},{e[2]:+.0f})" for e in error.tolist())
        print(
            f"condition {record.condition} ({record.offset[0]:+.3f}, {record.offset[1]:+.3f}) "
            f"rollout tip error mm {cells} final {float(rollouts.final_distance[i]):.3f} m"
        )
        samples = record.samples
        if samples.x.shape[0] == 0:
            print("    D_g fit: no stored successes")
            continue
        with torch.no_grad():
            mean = policy(samples.x[:, steps])
        diff = mean - samples.mean_cur[:, steps]
        relative = (diff.norm(dim=-1) / samples.mean_cur[:, steps].norm(dim=-1)).mean(0)
        prec = samples.prec_cur[:, steps]
        sigmas = (diff.unsqueeze(-2) @ prec @ diff.unsqueeze(-1)).flatten(-3).sqrt().mean(0)
        print(
            "    D_g fit: |mu_theta - mu_cur| / |mu_cur| "
            + " ".join(f"{v:.2f}" for v in relative)
            + "; in p_cur's standard deviations "
            + " ".join(f"{v:.1f}" for v in sigmas)
        )


if __name__ == "__main__":
    run(main)
