"""Where the global policy already succeeds at a new position, how good a controller does its
expansion make, and under how much exploration noise does it stay good?

    python scripts/research/transfer_start.py --run DIR [--scales 0 0.1 0.3 1] [--samples 10]

For each condition k >= 1 of a finished run, the policy checkpointed after condition k - 1
(the policy that condition k's learning started with) runs noiselessly at condition k's
position (the probe). Where it succeeds, its first-order expansion along the probe's states
(``K_t = d mu / dx``, ``k_t = mu(x_t) - K_t x_t``, ``jacobian_controller``) runs with the
local learner's initial exploration covariance times ``scale^2``, ``--samples`` rollouts per
scale (scale 0: noiselessly); and the policy itself runs with the same noise, for
comparison. Prints, per condition and scale, the success rate and the mean final distance
of each.
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.controllers import smoothed_noise
from lolgps_torch.lolgps.local import initial_controller
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import jacobian_controller, policy_actor
from lolgps_torch.policy.actor import PolicyActor
from lolgps_torch.sim.rollout import linear_gaussian_actor


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="finished run folder")
    parser.add_argument("--scales", type=float, nargs="+", default=[0.0, 0.1, 0.3, 1.0])
    parser.add_argument("--samples", type=int, default=10)
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    task = loaded.make_task()
    local = loaded.info.stream.local
    hold = initial_controller(task, local)
    T, dU = task.T, task.layout.dU
    threshold = task.config.world.success_threshold
    try:
        for record in loaded.records[1:]:
            k, offset = record.condition, record.offset
            policy = loaded.policy(k - 1)
            probe = task.sample(policy_actor(policy), [offset])
            head = f"condition {k} {offset}: probe {float(probe.final_distance[0]):.4f} m"
            if not probe.final_distance[0] < threshold:
                print(head + " (missed)")
                continue
            print(head)
            gen = torch.Generator().manual_seed(k)
            for scale in args.scales:
                n = 1 if scale == 0 else args.samples
                eps = smoothed_noise(n, T, dU, local.noise_smoothing, gen).to(task.device)
                expansion = jacobian_controller(policy, probe.x[0, :T], hold.cov * scale**2 + 1e-12 * torch.eye(dU, dtype=hold.cov.dtype))
                own = task.sample(linear_gaussian_actor(expansion, eps), [offset] * n)
                L = torch.linalg.cholesky(hold.cov)
                pol = task.sample(
                    PolicyActor(policy, scale * torch.einsum("tuv,ntv->ntu", L, eps)),
                    [offset] * n,
                )
                print(
                    f"   scale {scale:4.2f}: expansion {own.success.double().mean():.0%} "
                    f"({float(own.final_distance.mean()):.3f} m), policy "
                    f"{pol.success.double().mean():.0%} ({float(pol.final_distance.mean()):.3f} m)"
                )
    finally:
        task.close()


if __name__ == "__main__":
    run(main)
