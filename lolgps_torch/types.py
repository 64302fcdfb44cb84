"""Data containers shared by every box of the method.

Layouts, declared once:
  * controllers, dynamics and cost expansions are time-first: ``[T, ...]``;
  * sampled trajectories are sample-first: ``[N, T, ...]``.
``dX`` is the state size, ``dU`` the action size and ``dY = dX + dU`` the size of
the joint vector ``y = [x; u]``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor


class LinearGaussian(NamedTuple):
    """Time-varying linear-Gaussian controller ``p(u_t | x_t) = N(K_t x_t + k_t, cov_t)``.

    K: ``[T, dU, dX]``, k: ``[T, dU]``, cov: ``[T, dU, dU]`` (symmetric positive definite).
    """

    K: Tensor
    k: Tensor
    cov: Tensor

    @property
    def T(self) -> int:
        return int(self.K.shape[0])

    def chol(self) -> Tensor:
        """Lower Cholesky factor of ``cov``, ``[T, dU, dU]``."""
        return torch.linalg.cholesky(self.cov)

    def precision(self) -> Tensor:
        """``cov^{-1}``, ``[T, dU, dU]``."""
        return torch.cholesky_inverse(self.chol())

    def mean_action(self, x: Tensor) -> Tensor:
        """``K_t x_t + k_t`` for states ``x: [..., T, dX]`` -> ``[..., T, dU]``."""
        return torch.einsum("tux,...tx->...tu", self.K, x) + self.k


class LinearDynamics(NamedTuple):
    """Time-varying linear-Gaussian dynamics ``x_{t+1} ~ N(F_t [x_t; u_t] + f_t, cov_t)``.

    F: ``[T-1, dX, dX+dU]``, f: ``[T-1, dX]``, cov: ``[T-1, dX, dX]``;
    initial state ``x_0 ~ N(x0_mean, x0_cov)`` with x0_mean ``[dX]``, x0_cov ``[dX, dX]``.
    """

    F: Tensor
    f: Tensor
    cov: Tensor
    x0_mean: Tensor
    x0_cov: Tensor


# A model's step linearised at a batch: (x: [B, dX], u: [B, dU]) -> (F: [B, dX, dX + dU],
# f0: [B, dX]) with f(x, u) ~ F [x; u] + f0.
StepLinearizer = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]


class QuadraticCost(NamedTuple):
    """Per-step quadratic cost ``l_t(y) = 1/2 y^T C_t y + y^T c_t + cc_t`` with ``y = [x; u]``.

    C: ``[T, dY, dY]``, c: ``[T, dY]``, cc: ``[T]``.
    """

    C: Tensor
    c: Tensor
    cc: Tensor


class Trajectories(NamedTuple):
    """A batch of rollouts at one condition.

    x: ``[N, T, dX]`` states, u: ``[N, T, dU]`` actions, cost: ``[N, T]`` per-step cost,
    final_distance: ``[N]`` peg-tip distance to the hole-floor target at the last step (m),
    success: ``[N]`` bool, ``final_distance < success_threshold`` and no fault,
    final_state: ``[N, dX]`` the state ``x_T`` after the last action (stored, not learned from),
    fault: ``[N]`` bool, the arm's controller stopped the rollout (a limit passed).
    """

    x: Tensor
    u: Tensor
    cost: Tensor
    final_distance: Tensor
    success: Tensor
    final_state: Tensor
    fault: Tensor

    @property
    def N(self) -> int:
        return int(self.x.shape[0])

    @property
    def scored_distance(self) -> Tensor:
        """``[N]`` the final distance, inf where the rollout faulted: a rollout the arm's
        controller stopped never counts as reaching the hole."""
        return self.final_distance.masked_fill(self.fault, float("inf"))


class DistillBatch(NamedTuple):
    """States of successful samples with the two controllers' action Gaussians at those states.

    x: ``[M, dX]``; mean_cur, mean_pre: ``[M, dU]`` (``K_t x + k_t`` of p_cur and p_pre);
    prec_cur, prec_pre: ``[M, dU, dU]`` (``cov_t^{-1}``); has_pre: ``[M]`` bool, false where no
    p_pre existed (before the first S-step), where only ``KL(pi || p_cur)`` counts and
    ``mean_pre`` and ``prec_pre`` are ignored (zeros by convention).
    """

    x: Tensor
    mean_cur: Tensor
    prec_cur: Tensor
    mean_pre: Tensor
    prec_pre: Tensor
    has_pre: Tensor

    @property
    def M(self) -> int:
        return int(self.x.shape[0])


class ConditionSamples(NamedTuple):
    """The successful samples of one condition with their targets at sample time.

    x: ``[M, T, dX]``, u: ``[M, T, dU]``, cost: ``[M, T]``, final_distance: ``[M]``,
    mean_cur / mean_pre: ``[M, T, dU]`` action means of p_cur / p_pre at ``x``,
    prec_cur / prec_pre: ``[M, T, dU, dU]`` their precisions, has_pre: ``[M]`` bool (false where
    no p_pre existed; its mean and precision are then zeros), final_state: ``[M, dX]`` the state
    ``x_T`` after the last action (None where not recorded: replays written before it was).
    """

    x: Tensor
    u: Tensor
    cost: Tensor
    final_distance: Tensor
    mean_cur: Tensor
    prec_cur: Tensor
    mean_pre: Tensor
    prec_pre: Tensor
    has_pre: Tensor
    final_state: Tensor | None = None

    def to_batch(self) -> DistillBatch:
        """Flatten samples and time into the rows of a :class:`DistillBatch` (``M T`` rows)."""
        M, T, dX = self.x.shape
        dU = self.mean_cur.shape[-1]
        return DistillBatch(
            x=self.x.reshape(M * T, dX),
            mean_cur=self.mean_cur.reshape(M * T, dU),
            prec_cur=self.prec_cur.reshape(M * T, dU, dU),
            mean_pre=self.mean_pre.reshape(M * T, dU),
            prec_pre=self.prec_pre.reshape(M * T, dU, dU),
            has_pre=self.has_pre.repeat_interleave(T),
        )


class VisitedRows(NamedTuple):
    """States the global policy visited, labelled by a learnt condition's controllers: the
    S-step rows, and for each row the condition whose controllers labelled it and its time
    step, ``[R]`` each (integers)."""

    rows: DistillBatch
    condition: Tensor
    t: Tensor

    @property
    def R(self) -> int:
        return int(self.condition.shape[0])

    @classmethod
    def cat(cls, parts: list[VisitedRows]) -> VisitedRows:
        """The rows of ``parts``, one after another (at least one part)."""
        rows = DistillBatch(*(torch.cat(f) for f in zip(*(p.rows for p in parts), strict=True)))
        return cls(rows, torch.cat([p.condition for p in parts]), torch.cat([p.t for p in parts]))
