"""Normal-inverse-Wishart prior per time step from a GMM over recent trajectories.

Layout: inputs are sample-first ``X: [N, T, dA]``, ``Y: [N, T, dB]``; the prior is time-first,
``mu0: [T, D]``, ``Phi: [T, D, D]`` with ``D = dA + dB`` and the joint point ``z = [X; Y]``.
For dynamics ``X = [x_t; u_t]`` and ``Y = x_{t+1}``; for policy linearisation ``X = x_t`` and
``Y = pi(x_t)``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.dynamics.gmm import GaussianMixture
from lolgps_torch.errors import LolgpsError


class NIWPrior(NamedTuple):
    """Normal-inverse-Wishart prior on the joint Gaussian of ``z = [X; Y]`` at each step.

    mu0: ``[T, D]`` prior mean, Phi: ``[T, D, D]`` prior scatter (already multiplied by ``m``),
    m: pseudo-count of the mean, n0: pseudo-count of the covariance.
    """

    mu0: Tensor
    Phi: Tensor
    m: float
    n0: float


class GMMPrior:
    """GMM over the ``[X; Y]`` points of the last ``max_trajectories`` trajectories.

    ``update`` appends trajectories, drops the oldest beyond ``max_trajectories`` and refits the
    GMM (warm-started) with ``K = max(min_clusters, min(max_clusters, floor(P / min_points)))``
    clusters for ``P`` stored points. ``evaluate`` gives, per step t, the GMM moment-matched
    under the responsibilities of that step's points averaged over samples:
        ``w_t = mean_n r(z_{n,t})``, ``mu0_t = sum_k w_tk mu_k``,
        ``Phi_t = m sum_k w_tk [Sigma_k + (mu_k - mu0_t)(mu_k - mu0_t)^T]``,
        ``m = strength``, ``n0 = strength * max(0, (P - 2 - D) / P)``.
    ``n0`` is the original GPS choice (Levine et al.): the inverse-Wishart degrees of freedom
    ``P - 2 - D`` of the stored points normalised by ``P``, so ``n0 ~ 1`` for many points;
    it is clipped at zero when fewer than ``D + 2`` points are stored.

    :param max_trajectories: number of most recent trajectories kept.
    :param max_clusters: upper bound on K.
    :param min_clusters: lower bound on K.
    :param min_points_per_cluster: K is at most ``floor(P / min_points_per_cluster)``.
    :param strength: multiplier of both pseudo-counts.
    :param cov_reg: GMM covariance regulariser.
    :param em_iterations: maximum EM iterations per update.
    :param em_tolerance: EM stops when an iteration gains less than this many nats per point.
    :param seed: seed of the GMM's cold-start initialisation.
    """

    def __init__(
        self,
        max_trajectories: int = 20,
        max_clusters: int = 20,
        min_clusters: int = 2,
        min_points_per_cluster: int = 40,
        strength: float = 1.0,
        cov_reg: float = 1e-6,
        em_iterations: int = 100,
        em_tolerance: float = 1.0,
        seed: int = 0,
    ) -> None:
        if not 1 <= min_clusters <= max_clusters:
            raise LolgpsError(
                f"need 1 <= min_clusters <= max_clusters, got {min_clusters}, {max_clusters}"
            )
        self.max_trajectories = max_trajectories
        self.max_clusters = max_clusters
        self.min_clusters = min_clusters
        self.min_points_per_cluster = min_points_per_cluster
        self.strength = strength
        self.gmm = GaussianMixture(
            cov_reg=cov_reg, max_iterations=em_iterations, tolerance=em_tolerance, seed=seed
        )
        self.data: Tensor | None = None  # [M, T, D] stored trajectories, M <= max_trajectories

    def n_clusters(self, n_points: int) -> int:
        """Clusters for ``n_points`` points:
        ``K = max(min_clusters, min(max_clusters, floor(n_points / min_points_per_cluster)))``."""
        by_points = n_points // self.min_points_per_cluster
        return max(self.min_clusters, min(self.max_clusters, by_points))

    def update(self, X: Tensor, Y: Tensor) -> list[float]:
        """Store the trajectories ``[X; Y]`` (``[N, T, dA]``, ``[N, T, dB]``) and refit the GMM.

        Returns the EM trace of penalised log-likelihoods.
        """
        new = torch.cat([X, Y], dim=-1)  # [N, T, D]
        if self.data is not None and self.data.shape[1:] != new.shape[1:]:
            raise LolgpsError(
                f"prior holds trajectories of shape [T, D] = {list(self.data.shape[1:])}, "
                f"got {list(new.shape[1:])}"
            )
        data = new if self.data is None else torch.cat([self.data.to(new), new])
        self.data = data[-self.max_trajectories :]
        points = self.data.reshape(-1, self.data.shape[-1])  # [M T, D]
        return self.gmm.fit(points, self.n_clusters(points.shape[0]))

    def evaluate(self, X: Tensor, Y: Tensor) -> NIWPrior:
        """Prior per step for the current samples ``X: [N, T, dA]``, ``Y: [N, T, dB]``."""
        if self.data is None:
            raise LolgpsError("the GMM prior has no data yet: call update before evaluate")
        z = torch.cat([X, Y], dim=-1)  # [N, T, D]
        N, T, D = z.shape
        resp = self.gmm.responsibilities(z.reshape(N * T, D)).reshape(N, T, -1)
        mu0, cov = self.gmm.moments(resp.mean(0))  # [T, D], [T, D, D]
        n_points = self.data.shape[0] * self.data.shape[1]
        m = self.strength
        n0 = self.strength * max(0.0, (n_points - 2 - D) / n_points)
        return NIWPrior(mu0=mu0, Phi=m * cov, m=m, n0=n0)
