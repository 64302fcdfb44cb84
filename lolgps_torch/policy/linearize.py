"""Linearising the global policy around a condition's samples: ``p_pre`` (paper Algorithm 2,
line 14; ALGORITHM.md section 6).

Layout: samples are sample-first (``x: [N, T, dX]``); the result is time-first.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from lolgps_torch.dynamics import GMMPrior, gaussian_regression
from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.types import LinearGaussian


def linearize_policy(
    policy: GaussianPolicy, x: Tensor, prior: GMMPrior, regression_reg: float = 1e-6
) -> LinearGaussian:
    """``p_pre(u_t | x_t) = N(K_t x_t + k_t, S_t + Sigma_pi)`` fitted to the policy's means.

    The points ``[x_{n,t}; mu_theta(x_{n,t})]`` update ``prior`` (a GMM over this condition's
    recent trajectories) and give, per step, a normal-inverse-Wishart prior; the MAP joint
    Gaussian conditioned on x (:func:`lolgps_torch.dynamics.gaussian_regression`) gives
        ``K_t = Sigma_ux Sigma_xx^{-1}``, ``k_t = mu_u - K_t mu_x``,
        ``S_t = Sigma_uu - K_t Sigma_xx K_t^T``,
    and the policy's own noise is added: ``cov_t = S_t + Sigma_pi``. No gradient flows into the
    policy's weights.

    :param policy: the global policy (trained).
    :param x: states of the condition's current samples, ``[N, T, dX]``.
    :param prior: the condition's GMM prior over ``[x; pi(x)]``, updated in place.
    :param regression_reg: diagonal regulariser of ``Sigma_xx``.
    :return: ``K: [T, dU, dX]``, ``k: [T, dU]``, ``cov: [T, dU, dU]``.
    """
    if x.ndim != 3 or x.shape[-1] != policy.dX:
        raise LolgpsError(f"expected states [N, T, {policy.dX}], got {tuple(x.shape)}")
    with torch.no_grad():
        u = policy(x)  # [N, T, dU]
        prior.update(x, u)
        niw = prior.evaluate(x, u)
        K, k, S = gaussian_regression(x, u, niw, regression_reg)
        return LinearGaussian(K=K, k=k, cov=S + policy.covariance())


def linearize_policy_jacobian(policy: GaussianPolicy, x: Tensor) -> LinearGaussian:
    """``p_pre(u_t | x_t) = N(K_t x_t + k_t, S_t + Sigma_pi)`` from the policy's own Jacobian.

    With ``J_{n,t} = d mu_theta / d x`` at the sample states ``x_{n,t}`` (autograd, one batched
    pass), the gain and offset average the first-order expansions over the N samples:
        ``K_t = 1/N sum_n J_{n,t}``, ``k_t = 1/N sum_n (mu_theta(x_{n,t}) - K_t x_{n,t})``,
    and ``S_t = 1/N sum_n r_{n,t} r_{n,t}^T`` is the spread of the residuals
    ``r_{n,t} = mu_theta(x_{n,t}) - K_t x_{n,t} - k_t``. Unlike the regression of
    :func:`linearize_policy`, the gains hold in every state direction, including those the N
    samples do not span, so the controller follows the policy off the samples too. No gradient
    flows into the policy's weights.

    :param policy: the global policy (trained).
    :param x: states of the condition's current samples, ``[N, T, dX]``.
    :return: ``K: [T, dU, dX]``, ``k: [T, dU]``, ``cov: [T, dU, dU]``.
    """
    if x.ndim != 3 or x.shape[-1] != policy.dX:
        raise LolgpsError(f"expected states [N, T, {policy.dX}], got {tuple(x.shape)}")
    N, T, dX = x.shape
    with torch.no_grad():
        J = vmap(jacrev(policy.forward))(x.reshape(N * T, dX)).reshape(N, T, policy.dU, dX)
        u = policy(x)  # [N, T, dU]
        K = J.mean(0)
        Kx = torch.einsum("tux,ntx->ntu", K, x)
        k = (u - Kx).mean(0)
        residual = u - Kx - k
        S = torch.einsum("ntu,ntv->tuv", residual, residual) / N
        return LinearGaussian(K=K, k=k, cov=S + policy.covariance())
