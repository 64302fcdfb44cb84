"""Per-step linear-Gaussian dynamics fitted with a GMM normal-inverse-Wishart prior.

Layout: samples are sample-first (``x: [N, T, dX]``, ``u: [N, T, dU]``); fitted models are
time-first (``F: [T-1, dX, dX+dU]``). All steps are fitted in one batched linear-algebra call.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch import Tensor

from lolgps_torch.dynamics.model_prior import ModelPrior
from lolgps_torch.dynamics.prior import GMMPrior, NIWPrior
from lolgps_torch.errors import LolgpsError, NumericalError, check_fields
from lolgps_torch.types import LinearDynamics, StepLinearizer


def gaussian_regression(
    X: Tensor, Y: Tensor, prior: NIWPrior | None = None, sigma_reg: float = 1e-6
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-step linear-Gaussian regression ``Y_t ~ N(F_t X_t + f_t, cov_t)`` by a MAP joint fit.

    With ``z = [X; Y]``, sample mean ``mu`` and biased sample covariance ``S`` of the N samples
    at step t, the MAP covariance under the normal-inverse-Wishart prior (mu0, Phi, m, n0) is
        ``Sigma = [N S + Phi + (N m / (N + m)) (mu - mu0)(mu - mu0)^T] / (N + n0)``,
    plus ``sigma_reg`` on the diagonal of the X block; without a prior ``Sigma = S`` plus the
    same regulariser. Conditioning the joint Gaussian on X gives
        ``F = Sigma_YX Sigma_XX^{-1}``, ``f = mu_Y - F mu_X``, ``cov = Sigma_YY - F Sigma_XX F^T``.

    :param X: regressors ``[N, T, dA]``.
    :param Y: targets ``[N, T, dB]``.
    :param prior: per-step prior (``mu0: [T, dA+dB]``, ``Phi: [T, dA+dB, dA+dB]``) or None.
    :param sigma_reg: diagonal regulariser of ``Sigma_XX``.
    :return: ``F: [T, dB, dA]``, ``f: [T, dB]``, ``cov: [T, dB, dB]`` (symmetric).
    """
    if X.ndim != 3 or Y.ndim != 3 or X.shape[:2] != Y.shape[:2]:
        raise LolgpsError(f"expected X [N, T, dA] and Y [N, T, dB], got {X.shape} and {Y.shape}")
    N, _, dA = X.shape
    z = torch.cat([X, Y], dim=-1)  # [N, T, D]
    mean = z.mean(0)  # [T, D]
    centred = (z - mean).transpose(0, 1)  # [T, N, D]
    if prior is None:
        sigma = centred.mT @ centred / N  # [T, D, D], the biased sample covariance S
    else:
        diff = (mean - prior.mu0)[:, :, None]  # [T, D, 1]
        shrink = N * prior.m / (N + prior.m)
        # N S + Phi + shrink (mu - mu0)(mu - mu0)^T, with N S = sum_n (z_n - mu)(z_n - mu)^T.
        scatter = torch.baddbmm(prior.Phi, diff, diff.mT, alpha=shrink)
        sigma = torch.baddbmm(scatter, centred.mT, centred) / (N + prior.n0)
    eye = torch.eye(dA, dtype=X.dtype, device=X.device)
    sigma_xx = sigma[:, :dA, :dA] + sigma_reg * eye  # [T, dA, dA]
    sigma_xy = sigma[:, :dA, dA:]  # [T, dA, dB]
    chol, info = torch.linalg.cholesky_ex(sigma_xx)
    if bool(info.any()):
        raise LolgpsError(
            "regression covariance of [x; u] is not positive definite at steps "
            f"{info.nonzero().flatten().tolist()}; raise sigma_reg or use a prior"
        )
    F = torch.cholesky_solve(sigma_xy, chol).mT  # [T, dB, dA]
    f = mean[:, dA:] - (F @ mean[:, :dA, None]).squeeze(-1)  # [T, dB]
    cov = sigma[:, dA:, dA:] - F @ sigma_xx @ F.mT  # [T, dB, dB]
    return F, f, 0.5 * (cov + cov.mT)


PriorSource = Literal["gmm", "model"]


@dataclass(frozen=True)
class DynamicsConfig:
    """Dynamics fitting (docs/ALGORITHM.md section 4); GMM and prior defaults from the original GPS.

    :param use_prior: regularise the per-step fit with the GMM prior (off: plain regression).
    :param max_trajectories: trajectories of this condition kept for the GMM.
    :param max_clusters: upper bound on the number of GMM clusters.
    :param min_clusters: lower bound on the number of GMM clusters (1 and 1: a single Gaussian).
    :param min_points_per_cluster: K is at most ``floor(points / min_points_per_cluster)``.
    :param em_iterations: maximum EM iterations per update.
    :param em_tolerance: EM stops when an iteration gains less than this many nats per point.
        Loose on purpose: the prior needs only a rough mixture and the warm start carries EM
        on across iterations. Replaying the fits of stream conditions (KUKA and a Panda,
        ``scripts/bench/bench_fit.py --samples``), 1.0 took 2-3 EM iterations per update
        against 6 at 0.05, half the fit's time, at a held-out one-step error 0.99x (KUKA)
        and 0.83x (Panda) of 0.05's (docs/PERFORMANCE.md).
    :param cov_reg: GMM covariance regulariser (for a cluster of average size).
    :param regression_reg: diagonal regulariser of the ``[x; u]`` block of the MAP covariance.
    :param prior_strength: multiplier of the prior's pseudo-counts m and n0.
    :param initial_state_var: diagonal regulariser of the initial-state covariance.
    :param seed: seed of the GMM's cold-start initialisation.
    :param prior: gmm: the GMM prior alone; model: the arm's rigid-body model linearised at
        each step's samples, mixed with the GMM prior (when use_prior) where the model does
        not predict the samples (:class:`ModelPrior`). With either, the local learner plans
        its first controller on the model before the first sample (``LocalConfig.model_plans``).
    :param model_tolerance: relative one-step error of the model at which its weight is 1/2.
    """

    use_prior: bool = True
    max_trajectories: int = 20
    max_clusters: int = 20
    min_clusters: int = 2
    min_points_per_cluster: int = 40
    em_iterations: int = 100
    em_tolerance: float = 1.0
    cov_reg: float = 1e-6
    regression_reg: float = 1e-6
    prior_strength: float = 1.0
    initial_state_var: float = 1e-6
    seed: int = 0
    prior: PriorSource = "gmm"
    model_tolerance: float = 0.1

    def __post_init__(self) -> None:
        if self.prior not in get_args(PriorSource):
            raise LolgpsError(f"prior {self.prior!r}: one of {get_args(PriorSource)}")
        check_fields(self, {"model_tolerance": self.model_tolerance > 0})


def prior_from_config(c: DynamicsConfig) -> GMMPrior:
    """A :class:`GMMPrior` with the config's cluster rule, EM settings and strength (used for
    the dynamics and, over ``[x, pi(x)]``, for linearising the policy)."""
    return GMMPrior(
        max_trajectories=c.max_trajectories,
        max_clusters=c.max_clusters,
        min_clusters=c.min_clusters,
        min_points_per_cluster=c.min_points_per_cluster,
        strength=c.prior_strength,
        cov_reg=c.cov_reg,
        em_iterations=c.em_iterations,
        em_tolerance=c.em_tolerance,
        seed=c.seed,
    )


class DynamicsFitter:
    """Fits ``x_{t+1} ~ N(F_t [x_t; u_t] + f_t, cov_t)`` and ``x_0 ~ N(x0_mean, x0_cov)`` to the
    samples of one condition, each iteration, with a GMM prior over its recent trajectories.

    ``update`` feeds the new samples to the prior (``X = [x_t; u_t]``, ``Y = x_{t+1}`` for
    t < T-1), evaluates it at the same samples and runs :func:`gaussian_regression`. The initial
    state is ``x0_mean = mean_n x_{n,0}``, ``x0_cov = cov_n x_{n,0} + initial_state_var I``
    (unbiased sample covariance). ``em_history`` holds the EM trace of the last update.
    With ``prior="model"`` the GMM's prior is mixed into :class:`ModelPrior`'s, built on
    ``model`` (the arm's linearised step).
    """

    def __init__(
        self, config: DynamicsConfig | None = None, model: StepLinearizer | None = None
    ) -> None:
        self.config = config if config is not None else DynamicsConfig()
        c = self.config
        self.prior: GMMPrior | None = None
        self.em_history: list[float] = []
        if c.use_prior:
            self.prior = prior_from_config(c)
        self.model_prior: ModelPrior | None = None
        if c.prior == "model":
            if model is None:
                raise LolgpsError("prior 'model' needs the arm's model to linearise")
            self.model_prior = ModelPrior(model, c.prior_strength, c.model_tolerance)

    def update(self, x: Tensor, u: Tensor) -> LinearDynamics:
        """Update the prior with samples ``x: [N, T, dX]``, ``u: [N, T, dU]`` and fit to them."""
        if x.ndim != 3 or u.ndim != 3 or x.shape[:2] != u.shape[:2] or x.shape[1] < 2:
            raise LolgpsError(
                f"expected x [N, T, dX] and u [N, T, dU] with T >= 2, got "
                f"{tuple(x.shape)} and {tuple(u.shape)}"
            )
        if not bool(torch.isfinite(x).all() and torch.isfinite(u).all()):
            raise NumericalError("states or actions contain inf or NaN; cannot fit dynamics")
        X = torch.cat([x[:, :-1], u[:, :-1]], dim=-1)  # [N, T-1, dX+dU]
        Y = x[:, 1:]  # [N, T-1, dX]
        prior = None
        if self.prior is not None:
            self.em_history = self.prior.update(X, Y)
            prior = self.prior.evaluate(X, Y)
        if self.model_prior is not None:
            prior = self.model_prior.evaluate(X, Y, prior)
        F, f, cov = gaussian_regression(X, Y, prior, self.config.regression_reg)
        x0 = x[:, 0]  # [N, dX]
        x0_mean = x0.mean(0)
        centred = x0 - x0_mean
        eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
        x0_cov = centred.T @ centred / max(x.shape[0] - 1, 1) + self.config.initial_state_var * eye
        return LinearDynamics(F=F, f=f, cov=cov, x0_mean=x0_mean, x0_cov=x0_cov)
