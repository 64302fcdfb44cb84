"""Per time step, the one-step prediction error of the fitted dynamics and of the arm's
rigid-body model on held-out samples: where the model stops predicting, contact has started.

    python scripts/research/model_error.py --urdf robots/kuka_peg.urdf --hole 0 0 \\
        --iterations 6 --seed 0 [--dynamics-prior gmm] [--every 5]

The local learner of one hole runs --iterations iterations; its last controller is then
sampled twice: the first 5 rollouts fit the dynamics, the other 5 are held out. Per step t the
table gives, over the held-out rollouts, the relative error of the predicted joint-velocity
change, ``|qd_pred - qd_{t+1}| / |qd_{t+1} - qd_t|`` (mean), for the fit
``F_t [x_t; u_t] + f_t`` and for the model ``f(x_t, u_t)``, the model prior's weight w_t
(with ``--dynamics-prior model``), and the held-out rollouts' mean tip height above the hole
floor. The first step where the model's error exceeds 1 % is reported as contact.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import get_args

import torch
from torch import Tensor

from lolgps_torch.cli import add_task_arguments, run, task_config
from lolgps_torch.dynamics.fit import PriorSource
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
from lolgps_torch.task import PegTask


def relative_error(predicted: Tensor, x: Tensor, n: int) -> Tensor:
    """For predictions ``[N, T-1, dX]`` of the states ``x: [N, T, dX]`` after the first,
    the mean over rollouts of ``|qd_pred - qd'| / |qd' - qd|`` per step, ``[T-1]``."""
    qd, qd_next = x[:, :-1, n : 2 * n], x[:, 1:, n : 2 * n]
    error = (predicted[..., n : 2 * n] - qd_next).norm(dim=-1)
    return (error / (qd_next - qd).norm(dim=-1).clamp_min(1e-12)).mean(0)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser)
    parser.add_argument("--hole", type=float, nargs=2, default=(0.0, 0.0), metavar=("DX", "DY"))
    parser.add_argument("--iterations", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--dynamics-prior", choices=get_args(PriorSource), default=LocalConfig().dynamics.prior
    )
    parser.add_argument("--every", type=int, default=5, help="print every k-th step")
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    base = LocalConfig()
    config = replace(base, dynamics=replace(base.dynamics, prior=args.dynamics_prior))
    task = PegTask(task_config(args), n_worlds=config.samples)
    try:
        offset = (float(args.hole[0]), float(args.hole[1]))
        task.check_reachable(offset)
        learner = LocalLearner(task, offset, config, seed=args.seed)
        for i in range(args.iterations):
            _, _, record = iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
            print(f"iteration {i}: success {record.success_rate:.0%}", flush=True)
        fitting, held_out = learner.sample(learner.p_cur), learner.sample(learner.p_cur)
        dynamics = learner.fitter.update(fitting.x, fitting.u)
        weights = learner.fitter.model_prior.weights if learner.fitter.model_prior else None
        x = held_out.x  # [N, T, dX]
        xu = torch.cat([x[:, :-1], held_out.u[:, :-1]], -1)  # [N, T-1, dX+dU]
        fitted = torch.einsum("tij,ntj->nti", dynamics.F, xu) + dynamics.f
        model = task.model(x[:, :-1], held_out.u[:, :-1])
        n = task.layout.n_joints
        fit_error = relative_error(fitted, x, n)
        model_error = relative_error(model, x, n)
        height = x[:, :-1, task.layout.points][..., 2].mean(0)  # tip z above the floor target
    finally:
        task.close()
    print("| step | fit error | model error | model weight | tip height (m) |")
    print("|---|---|---|---|---|")
    for t in range(0, fit_error.shape[0], args.every):
        w = "-" if weights is None else f"{float(weights[t]):.2f}"
        print(f"| {t} | {float(fit_error[t]):.3g} | {float(model_error[t]):.3g} | {w} | "
              f"{float(height[t]):+.3f} |")  # fmt: skip
    above = (model_error > 0.01).nonzero()
    first = int(above[0]) if len(above) else None
    print(f"first step with model error > 1 %: {'none' if first is None else first}")


if __name__ == "__main__":
    run(main)
