"""What each round of the plan on the model does on the model itself: a condition's first
controller planned with K = 0 .. R C-steps, each rolled out noiselessly through the arm's
nonlinear model ``x' = f(x, u)`` (the simulator's free-space step) and through the simulator.

    python scripts/research/plan_rounds.py --run RUN [--conditions 0 6] [--rounds R] [--noisy N]

Per round K: the noiseless model rollout's total cost, its tip's final distance from the
target and its fastest joint; the simulator's noiseless final distance and fastest joint; then,
for N rollouts under the first samples' exploration noise (the same draws for every K), in the
model and in the simulator: the largest total cost over the noiseless hold's, and the median and
largest of the rollouts' fastest joint speeds.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import torch
from torch import Tensor

from lolgps_torch.cli import run, run_parser
from lolgps_torch.controllers.noise import smoothed_noise
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import initial_controller, planned_controller
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.sim.rollout import Actor, linear_gaussian_actor
from lolgps_torch.task import PegTask


def model_rollout(task: PegTask, act: Actor, x0: Tensor) -> tuple[Tensor, Tensor]:
    """``act`` on the model from ``x0: [N, dX]``: states ``[N, T+1, dX]``, actions
    ``[N, T, dU]``."""
    xs, us = [x0], []
    rows = slice(0, len(x0))
    for t in range(task.T):
        us.append(act(t, xs[-1], rows))
        xs.append(task.model(xs[-1], us[-1]))
    return torch.stack(xs, 1), torch.stack(us, 1)


def spread(task: PegTask, x: Tensor, u: Tensor, targets: Tensor, rest: float) -> str:
    """Rollouts ``x: [N, T(+1), dX]``: their largest total cost over the hold's ``rest`` and
    the median and largest of their fastest joint speeds (rad/s); "nan" where a state is not
    finite."""
    cost = task.cost.evaluate(x[:, : task.T], u, targets).sum(1)
    fastest = x[..., task.layout.qd].abs().amax((1, 2))
    return (f"{float(cost.max()) / rest:6.2f} {float(fastest.median()):6.1f} "
            f"{float(fastest.max()):6.1f}")  # fmt: skip


def main() -> None:
    parser = run_parser(__doc__, [0])
    parser.add_argument("--rounds", type=int, default=10, help="largest number of C-steps")
    parser.add_argument("--noisy", type=int, default=10, help="noisy rollouts per round")
    args = parser.parse_args()
    if args.rounds < 0 or args.noisy < 1:
        raise LolgpsError("--rounds must be >= 0 and --noisy >= 1")
    info = load_run(args.run).info
    info.check_conditions(args.conditions)
    warnings.simplefilter("ignore", UserWarning)  # the planning's KL warnings, as in the stream
    task = PegTask(info.task, n_worlds=1)
    lay = task.layout
    quiet = torch.zeros(1, task.T, lay.dU, dtype=torch.float64, device=task.device)
    try:
        for c in args.conditions:
            offset = info.conditions[c]
            targets = task.targets([offset])[0]
            hold = initial_controller(task, info.stream.local)
            x0 = torch.zeros(lay.dX, dtype=torch.float64, device=task.device)
            x0[lay.q] = task.q0
            x0[lay.points] = (task.kinematics.points(task.q0) - targets).flatten()
            print(f"condition {c} {offset}:")
            local = info.stream.local
            eps = smoothed_noise(args.noisy, task.T, lay.dU, local.noise_smoothing,
                                 torch.Generator().manual_seed(c)).to(task.device)  # fmt: skip
            print("  K  model cost  model final (m)  model fastest  sim final (m)  sim fastest"
                  "  | noisy model: cost/hold, median and largest speed | noisy sim: same")  # fmt: skip
            for k in range(args.rounds + 1):
                p, rest = planned_controller(task, targets, hold, replace(local, model_plans=k))
                p = p if k else hold
                x, u = model_rollout(task, linear_gaussian_actor(p, quiet), x0[None])
                cost = float(task.cost.evaluate(x[:, :-1], u, targets).sum())
                tip = float(x[0, -1, lay.points][:3].norm())
                fastest = float(x[0, :, lay.qd].abs().max())
                sim = task.sample(linear_gaussian_actor(p, quiet), [offset])
                sim_fast = float(sim.x[0, :, lay.qd].abs().max())
                noisy = linear_gaussian_actor(p, eps)
                xm, um = model_rollout(task, noisy, x0.expand(args.noisy, -1))
                model_bad = spread(task, xm, um, targets, rest)
                sims = task.sample(noisy, [offset] * args.noisy)
                sim_bad = spread(task, sims.x, sims.u, targets, rest)
                print(f"  {k:2d}  {cost:10.4g}  {tip:15.4f}  {fastest:13.1f}  "
                      f"{float(sim.final_distance[0]):13.4f}  {sim_fast:11.1f}  "
                      f"| {model_bad} | {sim_bad}", flush=True)  # fmt: skip
    finally:
        task.close()


if __name__ == "__main__":
    run(main)
