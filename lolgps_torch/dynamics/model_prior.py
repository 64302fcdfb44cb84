"""Normal-inverse-Wishart prior per time step from a model of the dynamics (docs/ALGORITHM.md
section 4.1): the arm's free-space step ``x' = f(x, u)`` linearised at each step's samples.

Layout as in :mod:`lolgps_torch.dynamics.prior`: samples ``X: [N, T, dA]`` (``X = [x_t; u_t]``),
``Y: [N, T, dB]`` (``Y = x_{t+1}``), the prior time-first with ``D = dA + dB``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lolgps_torch.dynamics.prior import NIWPrior
from lolgps_torch.errors import LolgpsError
from lolgps_torch.types import StepLinearizer


class ModelPrior:
    """The model's joint Gaussian of ``z = [X; Y]`` per step, mixed with a data prior where the
    model does not predict the samples (contact).

    At step t, with the samples' mean ``Xbar_t``, the model linearised there
    (``Y ~ F_t X + f_t``), the residuals ``r_n = Y_n - F_t X_n - f_t`` and the covariance
    ``Sigma_X`` of all the iteration's X points (pooled over steps, so that the model informs
    every direction, not only those the few samples of a step span):

        ``mu_t = [Xbar_t; F_t Xbar_t + f_t]``,
        ``Sigma_t = [[Sigma_X, Sigma_X F_t^T], [F_t Sigma_X, F_t Sigma_X F_t^T + W_t]]``,
        ``W_t = mean_n r_n r_n^T + residual_reg I``.

    The model's weight is ``w_t = 1 / (1 + (rho_t / tolerance)^2)`` with the relative one-step
    error ``rho_t = |r|_t / |Y - x|_t`` (norms over the step's samples; x the first dB entries
    of X). It falls where contact makes the model wrong, and also where the samples spread
    wider than the linearisation at their mean holds; it is ~1 where neither happens. Given a
    data prior (mu_d, Phi_d / m_d), the prior is the moment-matched mixture
        ``mu0 = w mu_t + (1 - w) mu_d``,
        ``Phi = m [w Sigma_t + (1 - w) Sigma_d + w (1 - w) (mu_t - mu_d)(mu_t - mu_d)^T]``,
    ``m = n0 = strength``; without one, the model's Gaussian alone.

    :param linearize: the model's linearisation at a batch of states and actions.
    :param strength: pseudo-counts m and n0.
    :param tolerance: relative one-step error at which the model's weight is 1/2.
    :param residual_reg: diagonal added to the residual covariance W_t.
    """

    def __init__(
        self,
        linearize: StepLinearizer,
        strength: float = 1.0,
        tolerance: float = 0.1,
        residual_reg: float = 1e-6,
    ) -> None:
        if not (strength > 0 and tolerance > 0 and residual_reg >= 0):
            raise LolgpsError(
                f"need strength > 0, tolerance > 0, residual_reg >= 0; got "
                f"{strength}, {tolerance}, {residual_reg}"
            )
        self.linearize, self.strength = linearize, strength
        self.tolerance, self.residual_reg = tolerance, residual_reg
        self.weights: Tensor | None = None  # [T] the model's weight w_t at the last evaluate

    def evaluate(self, X: Tensor, Y: Tensor, data: NIWPrior | None = None) -> NIWPrior:
        """Prior per step for ``X: [N, T, dA]``, ``Y: [N, T, dB]``, mixed with ``data``."""
        N, T, dA = X.shape
        dB = Y.shape[-1]
        mean = X.mean(0)  # [T, dA]
        F, f0 = self.linearize(mean[:, :dB], mean[:, dB:])  # [T, dB, dA], [T, dB]
        residual = Y - torch.einsum("tba,nta->ntb", F, X) - f0  # [N, T, dB]
        eye_b = torch.eye(dB, dtype=X.dtype, device=X.device)
        W = torch.einsum("nti,ntj->tij", residual, residual) / N + self.residual_reg * eye_b
        flat = X.reshape(N * T, dA)
        centred = flat - flat.mean(0)
        sigma_x = centred.T @ centred / (N * T)  # [dA, dA]
        cross = F @ sigma_x  # [T, dB, dA]
        sigma = torch.cat(
            [
                torch.cat([sigma_x.expand(T, dA, dA), cross.mT], -1),
                torch.cat([cross, cross @ F.mT + W], -1),
            ],
            -2,
        )  # [T, D, D]
        mu = torch.cat([mean, (F @ mean[..., None]).squeeze(-1) + f0], -1)  # [T, D]
        change = (Y - X[..., :dB]).square().sum((0, 2)).clamp_min(1e-300)
        rho = (residual.square().sum((0, 2)) / change).sqrt()  # [T]
        w = 1.0 / (1.0 + (rho / self.tolerance) ** 2)
        self.weights = w
        m = self.strength
        if data is not None:
            sigma_d = data.Phi / data.m
            diff = mu - data.mu0
            wc = w[:, None]
            mixed_mu = wc * mu + (1 - wc) * data.mu0
            spread = (w * (1 - w))[:, None, None] * diff[:, :, None] * diff[:, None, :]
            sigma = w[:, None, None] * sigma + (1 - w)[:, None, None] * sigma_d + spread
            mu = mixed_mu
        return NIWPrior(mu0=mu, Phi=m * sigma, m=m, n0=m)
