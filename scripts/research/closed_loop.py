"""Is a condition's first controller (planned on the arm's model) stable in closed loop on that
model?  Its noiseless rollout in the run's simulator, and along it the closed-loop matrix of
each step on the model linearised there, ``A_t = F_x,t + F_u,t K_t``.

    python scripts/research/closed_loop.py --run RUN [--conditions 0 2 6] [--model-plans K]

Per condition: the rollout's final distance and fastest joint, the largest spectral radius of
``A_t`` and the steps where it passes 1.05 (a perturbation grows by that factor per control
step there; the point features' integrators hold the radius at 1 otherwise).
``--model-plans K`` plans with K C-steps on the model instead of the run's number.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import torch

from lolgps_torch.cli import run, run_parser
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import LocalLearner
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.sim.rollout import linear_gaussian_actor
from lolgps_torch.task import PegTask

GROWING = 1.05  # spectral radius above which a step counts as amplifying


def main() -> None:
    parser = run_parser(__doc__, [0])
    parser.add_argument("--model-plans", type=int, help="C-steps on the model (default: the run's)")
    args = parser.parse_args()
    info = load_run(args.run).info
    info.check_conditions(args.conditions)
    warnings.simplefilter("ignore", UserWarning)  # the planning's KL warnings, as in the stream
    local = info.stream.local
    if args.model_plans is not None:
        if args.model_plans < 0:
            raise LolgpsError("--model-plans must be >= 0")
        local = replace(local, model_plans=args.model_plans)
    task = PegTask(info.task, n_worlds=1)
    lay = task.layout
    try:
        for c in args.conditions:
            learner = LocalLearner(task, info.conditions[c], local, seed=0)
            p = learner.p_cur
            quiet = torch.zeros(1, task.T, lay.dU, dtype=torch.float64, device=task.device)
            samples = task.sample(linear_gaussian_actor(p, quiet), [learner.offset])
            x, u = samples.x[0, :-1], samples.u[0, :-1]
            finite = bool(torch.isfinite(x).all() and torch.isfinite(u).all())
            F, _ = task.model.linearize(x, u)
            A = F[..., : lay.dX] + F[..., lay.dX :] @ p.K[: task.T - 1]
            radius = torch.linalg.eigvals(A).abs().amax(-1)
            fastest = float(samples.x[0, :, lay.qd].abs().max())
            print(f"condition {c}: final distance {float(samples.final_distance[0]):.4f} m, "
                  f"fastest joint {fastest:.1f} rad/s; spectral radius max "
                  f"{float(radius.max()):.3g}, above {GROWING} at {int((radius > GROWING).sum())} "
                  f"of {len(radius)} steps" + ("" if finite else " (states not finite)"),
                  flush=True)  # fmt: skip
    finally:
        task.close()


if __name__ == "__main__":
    run(main)
