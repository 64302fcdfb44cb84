"""How precisely a run's global policy reproduces its teachers, and how much error the closed
loop tolerates.

    python scripts/research/precision.py --run DIR [--checkpoint N] [--trials 6]
                                         [--biases 3 6 10 15] [--kicks 3 5] [--teachers]

It prints three tables:

- ``fit``: the policy's action error on D_g in the teachers' standard deviations,
  ``e = sqrt(d^T P_cur d)`` with ``d = mu_theta(x) - mu_cur(x)``, averaged over every stored
  successful state of every condition, per window of ten time steps.
- ``bias``: successes of noiseless rollouts at the training positions with a constant action
  bias ``c chol(Sigma_t) e`` added over steps 5-40, where ``Sigma_t`` is the condition's stored
  p_cur covariance, ``e`` a random unit vector per trial and ``c`` each of ``--biases``; for the
  teachers (each condition's p_cur, with ``--teachers``) and for the policy.
- ``kick``: successes after the peg is moved sideways by ``--kicks`` millimetres at step 15
  (both peg points translated in the table plane in a random direction per trial, through the
  pseudo-inverse of their Jacobian; joint velocities kept), for the same actors.

Every count is over ``--trials`` trials at each training position. The draws depend only on
``--seed``, so two runs (or two checkpoints) are compared on the same biases and kicks.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import cast

import torch
from torch import Tensor

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.retention import fit_by_window
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import GaussianPolicy
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld
from lolgps_torch.task import PegTask
from lolgps_torch.types import LinearGaussian

BIAS_STEPS = (5, 40)
KICK_STEP = 15
Act = Callable[[int, Tensor], Tensor]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    parser.add_argument("--checkpoint", type=int, default=None, help="policy after condition N")
    parser.add_argument("--trials", type=int, default=6, help="trials per position and setting")
    parser.add_argument("--biases", type=float, nargs="*", default=[3.0, 6.0, 10.0, 15.0])
    parser.add_argument("--kicks", type=float, nargs="*", default=[3.0, 5.0], help="mm")
    parser.add_argument("--teachers", action="store_true", help="measure the teachers too")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.trials < 1:
        raise LolgpsError(f"--trials {args.trials}: must be >= 1")
    return args


def rollout(
    task: PegTask,
    act: list[Act],
    offsets: Sequence[tuple[float, float]],
    bias: Tensor | None = None,
    kick: Tensor | None = None,
) -> Tensor:
    """Final distances ``[N]`` of noiseless rollouts, rollout i acted by ``act[i](t, x)`` (a
    ``[dX] -> [dU]`` callable) at ``offsets[i]``, with ``bias[i, t]`` (``[N, T, dU]``) added to
    its actions and the peg moved by ``kick[i]`` (m, ``[N, 2]``) at :data:`KICK_STEP`."""
    worlds, T = cast(list[PegWorld], task.sampler.worlds), task.T  # the default simulator's
    finals = []
    for start in range(0, len(offsets), len(worlds)):
        chunk = range(start, min(start + len(worlds), len(offsets)))
        used = worlds[: len(chunk)]
        for world, i in zip(used, chunk, strict=True):
            world.set_hole(offsets[i])
        x = [torch.from_numpy(w.reset(task.sampler.q0)) for w in used]
        for t in range(T):
            if kick is not None and t == KICK_STEP:
                x = [_kick(task, w, xi, kick[i]) for w, xi, i in zip(used, x, chunk, strict=True)]
            u = [act[i](t, xi) for xi, i in zip(x, chunk, strict=True)]
            if bias is not None:
                u = [ui + bias[i, t] for ui, i in zip(u, chunk, strict=True)]
            x = [torch.from_numpy(w.step(ui.numpy())) for w, ui in zip(used, u, strict=True)]
        finals += [w.tip_distance() for w in used]
    return torch.tensor(finals, dtype=torch.float64)


def _kick(task: PegTask, w: PegWorld, x: Tensor, shift: Tensor) -> Tensor:
    """Move both peg points of ``world`` by ``shift`` (m, in the table plane) through the
    least-squares joint change ``dq = J_xy^+ [shift; shift]``, keeping joint velocities."""
    lay = task.layout
    q = x[lay.q]
    _, jac = task.kinematics.points_and_jacobian(q)
    rows = jac[[0, 1, 3, 4]]  # x, y of tip and top
    dq = torch.linalg.pinv(rows) @ torch.cat([shift, shift])
    velocity = x[lay.point_velocities].numpy()
    for j, qj, qdj in zip(w.joint_ids, (q + dq).tolist(), x[lay.qd].tolist(), strict=True):
        pb.resetJointState(w.body, j, qj, qdj, physicsClientId=w.client)
    w._prev_points = (w.points() - w.targets).reshape(6) - velocity * w.config.dt
    return torch.from_numpy(w.observe())


def teacher_act(p: LinearGaussian) -> Act:
    return lambda t, x: p.K[t] @ x + p.k[t]


def policy_act(policy: GaussianPolicy) -> Act:
    def act(t: int, x: Tensor) -> Tensor:
        with torch.no_grad():
            return policy(x)

    return act


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    last = loaded.records[-1].condition if args.checkpoint is None else args.checkpoint
    policy = loaded.policy(last)
    print(f"policy after condition {last}")
    print(
        "fit (teacher sd) per 10 steps: "
        + " ".join(f"{v:.1f}" for v in fit_by_window(policy, loaded))
    )
    records = [r for r in loaded.records if r.p_cur is not None]
    teachers = [r.p_cur for r in records if r.p_cur is not None]
    if len(records) < len(loaded.records):
        print(f"({len(loaded.records) - len(records)} conditions without a stored p_cur skipped)")
    n = args.trials
    offsets = [r.offset for r in records for _ in range(n)]
    task = loaded.make_task(n_worlds=min(len(offsets), 8))
    gen = torch.Generator().manual_seed(args.seed)
    dU = task.layout.dU
    direction = torch.randn(len(offsets), dU, generator=gen, dtype=torch.float64)
    direction /= direction.norm(dim=-1, keepdim=True)
    angle = torch.rand(len(offsets), generator=gen, dtype=torch.float64) * 2 * torch.pi
    plane = torch.stack([angle.cos(), angle.sin()], -1)
    chol = torch.stack([p.chol() for p in teachers for _ in range(n)])  # [N, T, dU, dU]
    window = torch.zeros(task.T, dtype=torch.float64)
    window[BIAS_STEPS[0] : BIAS_STEPS[1] + 1] = 1.0
    actors = {"policy": [policy_act(policy)] * len(offsets)}
    if args.teachers:
        actors["teachers"] = [teacher_act(p) for p in teachers for _ in range(n)]
    total = len(offsets)
    try:
        for name, act in actors.items():
            cells = [f"plain {_count(task, act, offsets)}/{len(records)}"]
            for c in args.biases:
                bias = c * window[None, :, None] * torch.einsum("ntij,nj->nti", chol, direction)
                cells.append(f"bias {c:g}sd {_count(task, act, offsets, bias=bias)}/{total}")
            for mm in args.kicks:
                kick = plane * mm / 1000.0
                cells.append(f"kick {mm:g}mm {_count(task, act, offsets, kick=kick)}/{total}")
            print(f"{name}: " + ", ".join(cells))
    finally:
        task.close()


def _count(task: PegTask, act: list[Act], offsets: list[tuple[float, float]], **kw: Tensor) -> int:
    """Successes of :func:`rollout`; without a perturbation, one rollout per position."""
    if not kw:
        unique = list(dict.fromkeys(offsets))
        firsts = [offsets.index(o) for o in unique]
        finals = rollout(task, [act[i] for i in firsts], unique)
    else:
        finals = rollout(task, act, offsets, **kw)
    return int((finals < task.config.world.success_threshold).sum())


if __name__ == "__main__":
    run(main)
