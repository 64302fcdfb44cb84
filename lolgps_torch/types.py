"""Data containers shared by every box of the method.

Layouts, declared once:
  * controllers, dynamics and cost expansions are time-first: ``[T, ...]``;
  * sampled trajectories are sample-first: ``[N, T, ...]``.
``dX`` is the state size, ``dU`` the action size and ``dY = dX + dU`` the size of
the joint vector ``y = [x; u]``.
"""

from __future__ import annotations

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
    success: ``[N]`` bool, ``final_distance < success_threshold``.
    """

    x: Tensor
    u: Tensor
    cost: Tensor
    final_distance: Tensor
    success: Tensor

    @property
    def N(self) -> int:
        return int(self.x.shape[0])
