"""Does a model that knows contact help the dynamics prior where the peg meets the funnel?
MuJoCo's control step differentiated by central differences (contact included) against the
arm's free-space model (:class:`~lolgps_torch.sim.model.ControlStep`), as a linearisation and
as the model in the dynamics fit's prior (:class:`~lolgps_torch.dynamics.ModelPrior`).

    python scripts/research/contact_prior.py --run RUN [--conditions 0 4] [--samples 5]

At each condition of a finished run (its configuration and positions; the run may come from
either simulator), in MuJoCo: the first controller (planned on the model, as the stream's
first iteration samples it) is rolled out twice, ``samples`` rollouts with the noise of seed
1000 to fit on and as many with seed 2000 to test on. Each of four one-step predictions of
the joint speeds is scored on the test rollouts by its error ``|qd'_pred - qd'|`` (rad/s),
per phase: "free" where the peg's tip is more than 1 cm above the mouth, "hole" below that
(at the mouth's plates, in the hole, or on the table):

- ``model``: the free-space model linearised at the fitting rollouts' mean per step;
- ``differences``: MuJoCo's step linearised there by central differences;
- ``fit``: the dynamics fit of the stream (GMM and the free-space model as the prior);
- ``fit on differences``: the same fit with the differences as the prior's model.

It first checks that the differenced step is MuJoCo's own: stepped from each test state's
joint angles, speeds and action, the world gives the recorded next joint speeds.

MuJoCo's own ``mjd_transitionFD`` differentiates a physics step with respect to actuator
controls; this world's torques and Bullet-like damping enter as applied forces set between
the halves of each step, so the whole control step is differenced here instead, through
the world's own ``step``.  Only the default state (no action history) is supported.
"""

from __future__ import annotations

import statistics
import warnings
from dataclasses import replace

import mujoco
import numpy as np
import torch
from torch import Tensor

from lolgps_torch.cli import run, run_parser
from lolgps_torch.dynamics import DynamicsFitter
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import LocalLearner
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.model import ControlStep
from lolgps_torch.sim.mujoco_world import MujocoWorld
from lolgps_torch.task import PegTask
from lolgps_torch.types import LinearDynamics, Trajectories

ABOVE = 0.01  # m above the mouth: the tip higher than this is in free space


class MujocoDifferences:
    """``x' ~ F [x; u] + f0`` of a MuJoCo world's control step at states ``x: [B, dX]`` and
    actions ``u: [B, dU]``: the joints' step ``(q', qd', P(q') - P(q))`` differenced
    centrally in each of ``q`` (step ``eps_q``), ``qd`` (``eps_qd``) and ``u`` (``eps_u``),
    the world set to each state at rest of contact history, then assembled into the state's
    step as the model assembles its own (:meth:`ControlStep.assemble`)."""

    def __init__(
        self, world: MujocoWorld, model: ControlStep,
        eps_q: float = 1e-6, eps_qd: float = 1e-5, eps_u: float = 1e-4,
    ) -> None:  # fmt: skip
        self.world, self.model = world, model
        n = model.layout.n_joints
        self.eps = np.repeat([eps_q, eps_qd, eps_u], n)

    def step(self, inputs: np.ndarray) -> np.ndarray:
        """``(q', qd', P(q') - P(q))`` from ``(q, qd, u)`` (flat)."""
        world, n = self.world, self.model.layout.n_joints
        world.reset(inputs[:n])
        world.data.qvel[world.dof_ids] = inputs[n : 2 * n]
        mujoco.mj_forward(world.model, world.data)
        start = world.points()
        world.step(inputs[2 * n :])
        q, qd = world._joint_state()
        return np.concatenate([q, qd, (world.points() - start).reshape(6)])

    def __call__(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        lay = self.model.layout
        rows = []
        for xb, ub in zip(x.numpy(), u.numpy(), strict=True):
            inputs = np.concatenate([xb[lay.q], xb[lay.qd], ub])
            columns = []
            for k, eps in enumerate(self.eps):
                shift = np.zeros_like(inputs)
                shift[k] = eps
                columns.append((self.step(inputs + shift) - self.step(inputs - shift)) / (2 * eps))
            rows.append((self.step(inputs), np.stack(columns, -1)))
        n = lay.n_joints
        out = torch.from_numpy(np.stack([r for r, _ in rows]))
        J = torch.from_numpy(np.stack([j for _, j in rows]))
        return self.model.assemble(x, u, out[:, :n], out[:, n : 2 * n], out[:, 2 * n :], J)


def errors(F: Tensor, f: Tensor, test: Trajectories, qd: slice) -> Tensor:
    """``|qd'_pred - qd'|: [N, T-1]`` of per-step linear predictions ``F: [T-1, dX, dX+dU]``,
    ``f: [T-1, dX]`` on the test rollouts."""
    xu = torch.cat([test.x[:, :-1], test.u[:, :-1]], -1)
    predicted = torch.einsum("tij,ntj->nti", F, xu) + f
    return (predicted[..., qd] - test.x[:, 1:, qd]).norm(dim=-1)


def main() -> None:
    parser = run_parser(__doc__, [0, 4])
    parser.add_argument("--samples", type=int, default=5, help="rollouts to fit and to test")
    args = parser.parse_args()
    info = load_run(args.run).info
    if info.task.world.history:
        raise LolgpsError("only runs without an action history in the state are supported")
    if args.samples < 2:
        raise LolgpsError("--samples must be at least 2")
    info.check_conditions(args.conditions)
    warnings.simplefilter("ignore", UserWarning)  # the planning's KL warnings, as in the stream
    config = replace(info.task, sim="mujoco")
    task = PegTask(config, n_worlds=1)
    local = replace(info.stream.local, samples=args.samples)
    lay, depth = task.layout, config.world.depth
    world = build_world("mujoco", task.arm, config.world, task.geometry.nominal_mouth)
    assert isinstance(world, MujocoWorld)
    differences = MujocoDifferences(world, task.model)
    print("condition  phase  steps  model  differences  fit  fit on differences  (median rad/s)")
    try:
        for c in args.conditions:
            learner = LocalLearner(task, info.conditions[c], local, seed=0)
            world.set_hole(info.conditions[c])
            batches = []
            for seed in (1000, 2000):
                learner.generator.manual_seed(seed)
                batches.append(learner.sample(learner.p_cur))
            train, test = batches
            mean = torch.cat([train.x, train.u], -1)[:, :-1].mean(0)
            predictions: list[LinearDynamics | tuple[Tensor, Tensor]] = [
                task.model.linearize(mean[:, : lay.dX], mean[:, lay.dX :]),
                differences(mean[:, : lay.dX], mean[:, lay.dX :]),
                DynamicsFitter(local.dynamics, task.model.linearize).update(train.x, train.u),
                DynamicsFitter(local.dynamics, differences).update(train.x, train.u),
            ]
            scored = []
            for p in predictions:
                F, f = (p.F, p.f) if isinstance(p, LinearDynamics) else p
                scored.append(errors(F[: task.T - 1], f[: task.T - 1], test, lay.qd))
            exact = max(
                float(
                    abs(
                        differences.step(np.concatenate([x[lay.q], x[lay.qd], a]))[lay.qd]
                        - after[lay.qd]
                    ).max()
                )
                for xs, us in zip(test.x.numpy(), test.u.numpy(), strict=True)
                for x, a, after in zip(xs[:-1], us[:-1], xs[1:], strict=True)
            )
            print(f"{c:>9}  MuJoCo's step from each test state's q, qd and u: its next joint "
                  f"speeds to {exact:.1e} rad/s", flush=True)  # fmt: skip
            free = test.x[:, 1:, lay.points][..., 2] > depth + ABOVE
            for phase, mask in (("free", free), ("hole", ~free)):
                if not bool(mask.any()):
                    continue
                medians = [statistics.median(s[mask].tolist()) for s in scored]
                print(f"{c:>9}  {phase:>5}  {int(mask.sum()):>5}  "
                      + "  ".join(f"{m:.4f}" for m in medians), flush=True)  # fmt: skip
    finally:
        world.close()
        task.close()


if __name__ == "__main__":
    run(main)
