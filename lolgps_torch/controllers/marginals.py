"""State-action marginals of a linear-Gaussian controller under linear-Gaussian dynamics, and
the quantities computed from them: the controller KL and the expected cost (docs/ALGORITHM.md 3, 5).

Layout: time-first, with any leading batch dimensions ``...`` carried by the controller (for
example a batch of dual-variable candidates); dynamics and costs are unbatched ``[T, ...]``.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
import torch.nn.functional as nnf
from torch import Tensor

from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost


def _closed_loop_moments(
    policy: LinearGaussian, dynamics: LinearDynamics
) -> Iterator[tuple[Tensor, Tensor]]:
    """State mean ``[B, dX, 1]`` and covariance ``[B, dX, dX]`` of each step t = 0 .. T-1, with
    the controller's leading dimensions flattened to B.

    Closing the loop gives ``x_{t+1} = A_t x_t + b_t + w_t`` with ``A_t = Fx_t + Fu_t K_t``,
    ``b_t = Fu_t k_t + f_t``, ``w_t ~ N(0, Fu_t cov_t Fu_t^T + Sdyn_t)``, from
    ``N(x0_mean, x0_cov)``.  Only per-step tensors are built, so a batch of candidates never
    allocates ``[B, T, dX, dX]`` temporaries.
    """
    dX = dynamics.x0_mean.shape[-1]
    T, dU = policy.k.shape[-2:]
    K = policy.K.reshape(-1, T, dU, dX)
    B = K.shape[0]
    k = policy.k.reshape(B, T, dU, 1)[:, :-1].transpose(0, 1)  # [T-1, B, dU, 1]
    Fx = dynamics.F[:, None, :, :dX].expand(-1, B, -1, -1)  # [T-1, B, dX, dX]
    Fu = dynamics.F[:, None, :, dX:].expand(-1, B, -1, -1)  # [T-1, B, dX, dU]
    b = (Fu @ k + dynamics.f[:, None, :, None]).unbind(0)  # T-1 x [B, dX, 1]
    steps = zip(
        Fx.unbind(0),
        Fu.unbind(0),
        Fu.mT.unbind(0),
        K.unbind(1),
        policy.cov.reshape(B, T, dU, dU).unbind(1),
        b,
        dynamics.cov[:, None].expand(-1, B, -1, -1).unbind(0),
        strict=False,  # the controller has one more step than the dynamics
    )
    mean = dynamics.x0_mean.expand(B, dX).unsqueeze(-1)
    S = dynamics.x0_cov.expand(B, dX, dX)
    yield mean, S
    for Fx_t, Fu_t, FuT_t, K_t, cov_t, b_t, Sdyn_t in steps:
        A = torch.baddbmm(Fx_t, Fu_t, K_t)
        mean = torch.baddbmm(b_t, A, mean)
        S = torch.baddbmm(Sdyn_t, torch.bmm(A, S), A.mT)
        S = torch.baddbmm(S, torch.bmm(Fu_t, cov_t), FuT_t)
        yield mean, S


def state_marginals(policy: LinearGaussian, dynamics: LinearDynamics) -> tuple[Tensor, Tensor]:
    """State means ``[..., T, dX]`` and covariances ``[..., T, dX, dX]`` of ``policy``:
    ``mu_{t+1} = A_t mu_t + b_t``, ``S_{t+1} = A_t S_t A_t^T + Fu_t cov_t Fu_t^T + Sdyn_t`` from
    ``N(x0_mean, x0_cov)``, with ``A_t = Fx_t + Fu_t K_t`` and ``b_t = Fu_t k_t + f_t``."""
    means, covs = zip(*_closed_loop_moments(policy, dynamics), strict=True)
    batch, dX = policy.K.shape[:-3], policy.K.shape[-1]
    T = len(means)
    mu = torch.stack(means, dim=1).reshape(*batch, T, dX)
    return mu, torch.stack(covs, dim=1).reshape(*batch, T, dX, dX)


def joint_marginals(policy: LinearGaussian, mu_x: Tensor, sigma_x: Tensor) -> tuple[Tensor, Tensor]:
    """State-action marginals from state marginals: ``y = [x; u]``, ``u = K x + k + N(0, cov)``.

    :param mu_x: ``[..., T, dX]``. :param sigma_x: ``[..., T, dX, dX]``.
    :return: mu ``[..., T, dY]`` and sigma ``[..., T, dY, dY]`` (symmetrised).
    """
    dX = mu_x.shape[-1]
    eye = torch.eye(dX, dtype=mu_x.dtype, device=mu_x.device).expand(*policy.K.shape[:-2], dX, dX)
    G = torch.cat([eye, policy.K], dim=-2)  # [..., T, dY, dX], y = G x + [0; k] + [0; noise]
    mu_u = (policy.K @ mu_x.unsqueeze(-1)).squeeze(-1) + policy.k
    sigma = G @ sigma_x @ G.mT + nnf.pad(policy.cov, (dX, 0, dX, 0))
    return torch.cat([mu_x, mu_u], dim=-1), 0.5 * (sigma + sigma.mT)


def forward_pass(policy: LinearGaussian, dynamics: LinearDynamics) -> tuple[Tensor, Tensor]:
    """State-action marginals ``mu [..., T, dY]``, ``sigma [..., T, dY, dY]`` of ``policy``,
    propagated from the initial-state Gaussian through ``dynamics``."""
    return joint_marginals(policy, *state_marginals(policy, dynamics))


def _kl_from_moments(p: LinearGaussian, p_bar: LinearGaussian, m: Tensor, Z: Tensor) -> Tensor:
    """Expected KL ``[..., T]`` from the moments of the mean difference ``dK x + dk``:
    mean ``m [..., T, dU]`` and covariance ``Z = dK sigma_x dK^T`` ``[..., T, dU, dU]``."""
    dU = p.k.shape[-1]
    L_bar = torch.linalg.cholesky(p_bar.cov)
    P_bar = torch.cholesky_inverse(L_bar)  # [T, dU, dU]
    L = torch.linalg.cholesky(p.cov)
    trace = (P_bar * (p.cov + Z)).sum((-2, -1))
    quad = torch.einsum("...ti,tij,...tj->...t", m, P_bar, m)
    logdet_bar = 2.0 * torch.diagonal(L_bar, dim1=-2, dim2=-1).log().sum(-1)
    logdet = 2.0 * torch.diagonal(L, dim1=-2, dim2=-1).log().sum(-1)
    return 0.5 * (trace + quad - dU + logdet_bar - logdet)


def kl_divergence(p: LinearGaussian, p_bar: LinearGaussian, mu: Tensor, sigma: Tensor) -> Tensor:
    """Per-step ``E_{x ~ N(mu_x, sigma_x)} KL(p(.|x) || p_bar(.|x))`` ``[..., T]``, closed form.

    With ``P = cov_bar^{-1}``, ``dK = K - K_bar``, ``dk = k - k_bar``, ``m = dK mu_x + dk``:
    ``1/2 [tr(P cov) + tr(P dK sigma_x dK^T) + m^T P m - dU + log|cov_bar| - log|cov|]``.
    The sum over t is the trajectory KL.  Only the state part of ``mu``, ``sigma`` is used, so
    state marginals ``[..., T, dX]``, ``[..., T, dX, dX]`` are accepted too.
    """
    dX = p.K.shape[-1]
    dK = p.K - p_bar.K  # [..., T, dU, dX]
    m = (dK @ mu[..., :dX].unsqueeze(-1)).squeeze(-1) + p.k - p_bar.k
    return _kl_from_moments(p, p_bar, m, dK @ sigma[..., :dX, :dX] @ dK.mT)


def trajectory_kl(p: LinearGaussian, p_bar: LinearGaussian, dynamics: LinearDynamics) -> Tensor:
    """Per-step KL ``[..., T]`` of :func:`kl_divergence` under ``p``'s own state marginals,
    projected onto ``dK`` step by step instead of stacking state covariances (cheaper for a
    large batch of controllers)."""
    dU, dX = p.K.shape[-2:]
    T = p.K.shape[-3]
    batch = p.K.shape[:-3]
    dK = (p.K - p_bar.K).reshape(-1, T, dU, dX)  # [B, T, dU, dX]
    means, projected = [], []
    moments = _closed_loop_moments(p, dynamics)
    for dK_t, (mean, S) in zip(dK.unbind(1), moments, strict=True):
        means.append(mean)
        projected.append(torch.bmm(torch.bmm(dK_t, S), dK_t.mT))
    mu = torch.stack(means, dim=1).squeeze(-1)  # [B, T, dX]
    m = (dK @ mu.unsqueeze(-1)).squeeze(-1).reshape(*batch, T, dU) + p.k - p_bar.k
    Z = torch.stack(projected, dim=1).reshape(*batch, T, dU, dU)
    return _kl_from_moments(p, p_bar, m, Z)


def expected_cost(cost: QuadraticCost, mu: Tensor, sigma: Tensor) -> Tensor:
    """Per-step expected quadratic cost ``[..., T]`` under ``y ~ N(mu, sigma)`` (exact for a
    quadratic; the Laplace approximation of the true cost):
    ``1/2 tr(C sigma) + 1/2 mu^T C mu + mu^T c + cc``."""
    trace = (cost.C * sigma.mT).sum((-2, -1))
    quad = torch.einsum("...ti,tij,...tj->...t", mu, cost.C, mu)
    return 0.5 * trace + 0.5 * quad + (mu * cost.c).sum(-1) + cost.cc
