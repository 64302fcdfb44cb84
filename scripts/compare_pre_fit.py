"""Compare the two ways of linearising the global policy into p_pre on a finished run.

    python scripts/compare_pre_fit.py --run DIR [--condition C] [--checkpoint K] [--samples 5]

Takes the policy checkpointed after condition K (default: the last) and the first ``--samples``
stored successful rollouts of condition C from the run's replay, fits p_pre around their
states by GMM regression (ALGORITHM.md section 6) and by the policy's Jacobian, and prints for
each: the mean action error at those states and the final distance of its noiseless rollout at
condition C, next to the policy's own. A p_pre that follows the policy ends where the policy
ends.
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.dynamics import prior_from_config
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import checkpoint_dir, read_run
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.policy import (
    GaussianPolicy,
    linearize_policy,
    linearize_policy_jacobian,
    policy_actor,
)
from lolgps_torch.sim.rollout import linear_gaussian_actor
from lolgps_torch.task import PegTask, task_config_from_dict


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    parser.add_argument("--condition", type=int, default=0, help="condition to test at")
    parser.add_argument("--checkpoint", type=int, default=None, help="policy after condition K")
    parser.add_argument("--samples", type=int, default=5, help="rollouts to linearise around")
    args = parser.parse_args()
    info = read_run(args.run)
    replay = ReplayBuffer(f"{args.run}/replay.h5")
    last = args.checkpoint if args.checkpoint is not None else len(replay.conditions()) - 1
    policy = GaussianPolicy.load(checkpoint_dir(args.run, last))
    record = replay.read_condition(args.condition)
    x = record.samples.x[: args.samples]
    if x.shape[0] == 0:
        raise LolgpsError(f"condition {args.condition} has no stored rollouts")
    task = PegTask(task_config_from_dict(info.task), n_worlds=1)
    zero = torch.zeros(1, task.T, task.layout.dU, dtype=torch.float64)
    fits = {
        "gmm": linearize_policy(policy, x, prior_from_config(LocalConfig().dynamics)),
        "jacobian": linearize_policy_jacobian(policy, x),
    }
    with torch.no_grad():
        u = policy(x)
    print(
        f"policy after condition {last} at condition {args.condition} {record.offset}: "
        f"mean |action| {float(u.norm(dim=-1).mean()):.2f}, noiseless final distance "
        f"{float(task.sample(policy_actor(policy), [record.offset]).final_distance[0]):.4f} m"
    )
    for name, p_pre in fits.items():
        error = float((p_pre.mean_action(x) - u).norm(dim=-1).mean())
        gain = float(p_pre.K.flatten(1).norm(dim=1).median())
        final = task.sample(linear_gaussian_actor(p_pre, zero), [record.offset]).final_distance
        print(
            f"p_pre by {name:8s}: mean action error at the samples {error:.3f}, median gain "
            f"norm {gain:.0f}, noiseless final distance {float(final[0]):.4f} m"
        )
    task.close()


if __name__ == "__main__":
    run(main)
