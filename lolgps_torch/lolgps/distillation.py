"""D_g and the S-step over it (docs/ALGORITHM.md sections 7-8).

A condition's D_g is its successful rollouts, each state labelled with the action means and
precisions of the controllers (p_cur, p_pre) that ``StreamLearner.teacher`` picks. The S-step fits
the global policy to

    sum over conditions m, rows (x, t) of D_g(m):  KL(pi(.|x) || p_cur,t(.|x))
                                                 + lambda KL(pi(.|x) || p_pre,t(.|x))   (eq. 8)

on the new conditions' D_g, ``augment`` kinematically consistent perturbed copies of their
states (labelled by the same linear-Gaussian controllers, which are defined at any state), and
the earlier conditions' D_g from the replay, with the labelled states the policy visited in
earlier S-steps (:mod:`lolgps_torch.lolgps.onpolicy` visits them and checks the result in
closed loop).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.replay import ConditionRecord
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, distill
from lolgps_torch.policy.guard import Guard, fit_guard
from lolgps_torch.policy.sstep import intra_op_threads
from lolgps_torch.state import StateLayout
from lolgps_torch.task import PegTask
from lolgps_torch.types import (
    ConditionSamples,
    DistillBatch,
    LinearGaussian,
    Trajectories,
    VisitedRows,
)


def guard_of(
    data: list[ConditionSamples],
    layout: StateLayout,
    cfg: PolicyConfig,
    depth: float,
    velocity: Tensor,
) -> Guard | None:
    """The guard :func:`fit_guard` fits to the conditions' D_g ``data`` (None where none holds
    a full rollout; states as ``layout`` says), with ``cfg``'s margins and the arm's velocity
    limits ``velocity [dU]``; its hover point, if any, ``cfg.guard_hover`` above the mouth of a
    hole ``depth`` (m) deep."""
    full = [d for d in data if d.final_state is not None and d.x.shape[0] > 0]
    if not full:
        return None
    x = torch.cat([torch.cat([d.x, d.final_state[:, None]], 1) for d in full])  # type: ignore[index]  # final_state checked above
    mean_cur = torch.cat([d.mean_cur for d in full])
    with intra_op_threads(cfg.num_threads):  # as the S-step: the same bits in any process
        hover = None if cfg.guard_hover is None else (depth + cfg.guard_hover, cfg.guard_hover_time)
        return fit_guard(
            x, mean_cur, layout, cfg.guard_torque, cfg.guard_speed, cfg.guard_window,
            cfg.guard_retreat, cfg.guard_brake, hover, cfg.guard_limit * velocity,
        )  # fmt: skip


class Labels(NamedTuple):
    """The teachers whose means and precisions label a condition's D_g (p_cur, p_pre), and
    the iteration at which that p_cur acts."""

    p_cur: LinearGaussian
    p_pre: LinearGaussian | None
    iteration: int


class Labelled(NamedTuple):
    """A condition's hole offset, D_g and the labels it was made with."""

    offset: tuple[float, float]
    data: ConditionSamples
    labels: Labels


def controller_targets(p: LinearGaussian, x: Tensor) -> tuple[Tensor, Tensor]:
    """Means ``[M, T, dU]`` and precisions ``[M, T, dU, dU]`` of ``p`` at states ``[M, T, dX]``."""
    mean = p.mean_action(x)
    prec = p.precision()
    return mean, prec.expand(x.shape[0], *prec.shape)


def targets(x: Tensor, labels: Labels) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Means and precisions of p_cur and p_pre at states ``x: [M, T, dX]`` (zeros and
    ``has_pre`` false without p_pre)."""
    with torch.no_grad():
        mean_cur, prec_cur = controller_targets(labels.p_cur, x)
        if labels.p_pre is not None:
            mean_pre, prec_pre = controller_targets(labels.p_pre, x)
        else:
            mean_pre, prec_pre = torch.zeros_like(mean_cur), torch.zeros_like(prec_cur)
    has_pre = torch.full((x.shape[0],), labels.p_pre is not None, dtype=torch.bool, device=x.device)
    return mean_cur, prec_cur, mean_pre, prec_pre, has_pre


def label(task: PegTask, kept: list[Trajectories], labels: Labels) -> ConditionSamples:
    """D_g: the successful rollouts ``kept`` with the labels' action means and precisions at
    their states (one coherent feedback law per condition; M may be 0)."""
    if kept:
        x, u, cost, final, last = (
            torch.cat([getattr(k, name) for k in kept])
            for name in ("x", "u", "cost", "final_distance", "final_state")
        )
    else:
        x = torch.zeros(0, task.T, task.layout.dX, dtype=torch.float64, device=task.device)
        u = torch.zeros(0, task.T, task.layout.dU, dtype=torch.float64, device=task.device)
        cost, final, last = x.new_zeros(0, task.T), x.new_zeros(0), x.new_zeros(0, task.layout.dX)
    return ConditionSamples(x, u, cost, final, *targets(x, labels), final_state=last)


def consistent_states(task: PegTask, x: Tensor, offset: tuple[float, float]) -> Tensor:
    """States ``[..., dX]`` with their points and point velocities recomputed from q and
    q-dot: ``p(q) - p*`` and ``J(q) q-dot``."""
    lay = task.layout
    points, jac = task.kinematics.points_and_jacobian(x[..., lay.q])
    out = x.clone()
    out[..., lay.points] = (points - task.targets([offset])[0]).flatten(-2)
    out[..., lay.point_velocities] = (jac @ x[..., lay.qd].unsqueeze(-1)).squeeze(-1)
    return out


class Distiller:
    """The S-step with replay: owns nothing but the settings, the replay it reads and the
    records it has read from it.

    :param augment: perturbed copies of each new D_g state.
    :param augment_scale: their size, in per-step standard deviations of D_g's states (q and
        q-dot are perturbed; the points and their velocities follow by kinematics).
    :param replay: the earlier conditions' D_g, or None to distil the new ones only.
    """

    def __init__(
        self,
        task: PegTask,
        config: PolicyConfig,
        augment: int,
        augment_scale: float,
        replay: ReplayBuffer | None,
    ) -> None:
        self.task, self.config, self.replay = task, config, replay
        self.augment, self.augment_scale = augment, augment_scale
        self._records: dict[int, ConditionRecord] = {}

    def __call__(
        self,
        policy: GaussianPolicy,
        new: list[Labelled],
        seed: int,
        emphasis: frozenset[int] = frozenset(),
        config: PolicyConfig | None = None,
        visited: VisitedRows | None = None,
    ) -> list[float]:
        """Fit ``policy`` on the ``new`` conditions' D_g with their perturbed copies, plus the
        replay (its D_g and the states the policy visited in earlier S-steps) and ``visited``;
        returns the losses (empty when there is no data).

        :param emphasis: conditions whose D_g rows enter twice, by place: ``0 .. R-1`` the
            replay's conditions in order, ``R + i`` the ``new`` item ``i``.
        :param config: the S-step's settings (default: the distiller's).
        :param visited: labelled states the policy visited in this S-step so far.
        """
        gen = torch.Generator().manual_seed(seed)
        stored = self.stored()
        batches = []
        for place, record in enumerate(stored):
            batches += [record.samples.to_batch()] * (2 if place in emphasis else 1)
        for place, item in enumerate(new, start=len(stored)):
            own = [item.data.to_batch()]
            if item.data.x.shape[0] > 1 and self.augment > 0:
                own.append(self._augmented(item, gen))
            batches += own * (2 if place in emphasis else 1)
        visits = [r.visited for r in stored if r.visited is not None]
        batches += [v.rows for v in [*visits, *([visited] if visited is not None else [])]]
        batch = DistillBatch(*(torch.cat(f) for f in zip(*batches, strict=True)))
        if batch.x.shape[0] == 0:
            return []
        losses = distill(policy, batch, config or self.config, gen)
        if self.config.guard:
            self._set_guard(policy, [r.samples for r in stored] + [item.data for item in new])
        return losses

    def _set_guard(self, policy: GaussianPolicy, data: list[ConditionSamples]) -> None:
        """The policy's guard from every condition's D_g (:func:`guard_of`)."""
        velocity = torch.tensor(self.task.arm.velocity, dtype=torch.float64)
        guard = guard_of(
            data, self.task.layout, self.config, self.task.config.world.depth, velocity
        )
        if guard is not None:
            policy.set_guard(guard)

    def stored(self) -> list[ConditionRecord]:
        """The replay's conditions in order; each is read from the file once (the replay only
        grows) and kept."""
        if self.replay is None:
            return []
        conditions = self.replay.conditions()
        for index in conditions:
            if index not in self._records:
                self._records[index] = self.replay.read_condition(index, self.task.device)
        return [self._records[index] for index in conditions]

    def _augmented(self, item: Labelled, gen: torch.Generator) -> DistillBatch:
        """``augment`` copies of D_g's states, q and q-dot perturbed by ``augment_scale`` times
        the per-step spread of the condition's successes, labelled by its controllers."""
        x = item.data.x
        spread = (x - x.mean(0)).std(0)  # [T, dX]
        noise = torch.randn(self.augment, *x.shape, generator=gen, dtype=x.dtype)
        x_aug = (x + self.augment_scale * spread * noise.to(x.device)).flatten(0, 1)
        x_aug = consistent_states(self.task, x_aug, item.offset)
        aug = ConditionSamples(
            x_aug, x_aug[..., :0], x_aug[..., 0], x_aug[:, 0, 0], *targets(x_aug, item.labels)
        )
        return aug.to_batch()
