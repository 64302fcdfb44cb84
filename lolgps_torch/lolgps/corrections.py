"""Policy corrections: the global policy's own states, labelled by the local controllers.

The S-step fits pi_theta on D_g, the states the local controllers visited. Run alone, the policy
drifts from those states and its small errors compound, most visibly at the hole's mouth, where
a few millimetres decide between entering and resting on the plate. After a first fit, each
round rolls the policy out at the conditions learnt so far, keeps the states it reached while
still near that condition's successful trajectories, labels them with the condition's final
p_cur and p_pre (linear-Gaussian, so defined at any state), adds them to the S-step's rows and
fits again (data aggregation, as in DAgger; Ross et al., 2011). The rows visited in the last
round are the policy's states under the current weights, so the fit is corrected where the
policy actually goes.

A state is kept while its end-effector points stay within ``radius`` of the mean points of the
condition's D_g at the same step (cut at the first step outside): far from where a linear
controller was fitted its labels stop being sensible.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.task import PegTask
from lolgps_torch.types import DistillBatch, LinearGaussian


@dataclass(frozen=True)
class CorrectionConfig:
    """Policy-correction rounds of each S-step.

    :param rounds: correction rounds after the first fit (0: off, the default: on two seeds of
        the default stream two rounds did not raise the policy's success, docs/RESULTS.md).
    :param rollouts: policy rollouts per condition and round: the noiseless one, then ones with
        the policy's own noise ``Sigma_pi``.
    :param steps: Adam steps of each round's refit.
    :param radius: distance (m) from the D_g mean end-effector points beyond which visited states
        are dropped.
    """

    rounds: int = 0
    rollouts: int = 2
    steps: int = 1000
    radius: float = 0.15


class Teacher(NamedTuple):
    """A learnt condition: its hole offset, final controllers and the mean end-effector points
    of its D_g per step, ``reference: [T, 6]``."""

    offset: tuple[float, float]
    p_cur: LinearGaussian
    p_pre: LinearGaussian | None
    reference: Tensor


def teacher_reference(task: PegTask, x: Tensor) -> Tensor:
    """Mean end-effector points per step ``[T, 6]`` of successful states ``x: [M, T, dX]``."""
    return x[..., task.layout.points].mean(0)


def visit(
    task: PegTask,
    policy: GaussianPolicy,
    teachers: list[Teacher],
    config: CorrectionConfig,
    generator: torch.Generator,
) -> DistillBatch:
    """Roll the policy out ``config.rollouts`` times at every teacher's offset (the first
    noiseless) and return the kept states with their teachers' action targets.

    Targets are ``K_t x + k_t`` and ``cov_t^{-1}`` of p_cur (and p_pre, where the teacher has one)
    at the visited ``x_t``; rows are the kept ``(rollout, t)`` pairs.
    """
    R, T, dU = config.rollouts, task.T, task.layout.dU
    offsets = [teacher.offset for teacher in teachers for _ in range(R)]
    eps = torch.randn(len(offsets), T, dU, generator=generator, dtype=torch.float64)
    eps[::R] = 0.0
    x = task.sample(policy_actor(policy, eps.to(task.device)), offsets).x  # [C R, T, dX]
    x = x.reshape(len(teachers), R, T, -1)
    rows: list[DistillBatch] = []
    for teacher, xs in zip(teachers, x, strict=True):
        gap = (xs[..., task.layout.points] - teacher.reference).norm(dim=-1)  # [R, T]
        keep = torch.cumprod(gap < config.radius, dim=1).bool()
        kept = xs[keep]  # [rows, dX]
        t = torch.arange(T, device=xs.device).expand(R, T)[keep]
        rows.append(_labelled(kept, t, teacher))
    return DistillBatch(*(torch.cat(f) for f in zip(*rows, strict=True)))


def _labelled(x: Tensor, t: Tensor, teacher: Teacher) -> DistillBatch:
    """Rows ``x: [M, dX]`` at steps ``t: [M]`` with the teacher's action Gaussians."""

    def at(p: LinearGaussian) -> tuple[Tensor, Tensor]:
        mean = torch.einsum("mux,mx->mu", p.K[t], x) + p.k[t]
        return mean, p.precision()[t]

    mean_cur, prec_cur = at(teacher.p_cur)
    if teacher.p_pre is not None:
        mean_pre, prec_pre = at(teacher.p_pre)
    else:
        mean_pre, prec_pre = torch.zeros_like(mean_cur), torch.zeros_like(prec_cur)
    has_pre = torch.full((x.shape[0],), teacher.p_pre is not None, device=x.device)
    return DistillBatch(x, mean_cur, prec_cur, mean_pre, prec_pre, has_pre)
