"""Linearising the global policy around a condition's samples: ``p_pre`` (paper Algorithm 2,
line 14; docs/ALGORITHM.md section 6).

Layout: samples are sample-first (``x: [N, T, dX]``); the result is time-first.
"""

from __future__ import annotations

import torch
from torch import Tensor

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


def jacobian_controller(policy: GaussianPolicy, x: Tensor, cov: Tensor) -> LinearGaussian:
    """The policy's first-order expansion along one trajectory, as a controller:

        ``K_t = d mu_theta / dx (x_t)``,  ``k_t = mu_theta(x_t) - K_t x_t``,  covariance ``cov``

    so that ``K_t x + k_t = mu_theta(x_t) + K_t (x - x_t)``: the policy's own feedback near the
    states ``x: [T, dX]`` it visits (autograd Jacobians, exact, not a regression on samples).

    :param cov: the controller's covariance, ``[T, dU, dU]``.
    :return: ``K: [T, dU, dX]``, ``k: [T, dU]``, ``cov``.
    """
    if x.ndim != 2 or x.shape[-1] != policy.dX or cov.shape != (x.shape[0], policy.dU, policy.dU):
        raise LolgpsError(
            f"expected states [T, {policy.dX}] and covariances [T, {policy.dU}, {policy.dU}], "
            f"got {tuple(x.shape)} and {tuple(cov.shape)}"
        )
    with torch.no_grad():
        K = torch.func.vmap(torch.func.jacrev(policy))(x)  # [T, dU, dX]
        k = policy(x) - (K @ x.unsqueeze(-1)).squeeze(-1)
    return LinearGaussian(K=K, k=k, cov=cov)
