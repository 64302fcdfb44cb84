"""Linear-Gaussian controllers: KL, marginals and expected cost against Monte Carlo; mixing,
the hold controller and smoothed noise."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from lolgps_torch.controllers import (
    expected_cost,
    forward_pass,
    hold_controller,
    kl_divergence,
    mix,
    smoothed_noise,
    state_marginals,
    trajectory_kl,
)
from lolgps_torch.errors import LolgpsError
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost

DT = torch.float64


def _spd(n: int, *batch: int, g: torch.Generator, scale: float = 1.0) -> Tensor:
    M = torch.randn(*batch, n, n, generator=g, dtype=DT)
    return scale * (M @ M.mT / n + 0.2 * torch.eye(n, dtype=DT))


def _controller(T: int, dX: int, dU: int, g: torch.Generator) -> LinearGaussian:
    K = 0.3 * torch.randn(T, dU, dX, generator=g, dtype=DT)
    return LinearGaussian(K, torch.randn(T, dU, generator=g, dtype=DT), _spd(dU, T, g=g))


def _system(T: int, dX: int, dU: int, g: torch.Generator) -> LinearDynamics:
    A = torch.eye(dX, dtype=DT) + 0.2 * torch.randn(T - 1, dX, dX, generator=g, dtype=DT)
    B = 0.5 * torch.randn(T - 1, dX, dU, generator=g, dtype=DT)
    return LinearDynamics(
        F=torch.cat([A, B], dim=-1),
        f=0.1 * torch.randn(T - 1, dX, generator=g, dtype=DT),
        cov=_spd(dX, T - 1, g=g, scale=0.05),
        x0_mean=torch.randn(dX, generator=g, dtype=DT),
        x0_cov=_spd(dX, g=g, scale=0.3),
    )


def _log_density(policy: LinearGaussian, x: Tensor, u: Tensor) -> Tensor:
    """log p(u | x) for samples ``x [N, T, dX]``, ``u [N, T, dU]`` -> ``[N, T]``."""
    L = policy.chol()  # [T, dU, dU]
    z = torch.linalg.solve_triangular(L, (u - policy.mean_action(x)).unsqueeze(-1), upper=False)
    logdet = 2.0 * torch.diagonal(L, dim1=-2, dim2=-1).log().sum(-1)
    dU = u.shape[-1]
    return -0.5 * (z.squeeze(-1).square().sum(-1) + logdet + dU * math.log(2 * math.pi))


def _rollouts(
    policy: LinearGaussian, dynamics: LinearDynamics, N: int, g: torch.Generator
) -> tuple[Tensor, Tensor]:
    """Sampled states ``[N, T, dX]`` and actions ``[N, T, dU]`` of the linear system."""
    T, dU, dX = policy.K.shape
    L, L_dyn = policy.chol(), torch.linalg.cholesky(dynamics.cov)
    x = (
        dynamics.x0_mean
        + torch.randn(N, dX, generator=g, dtype=DT) @ torch.linalg.cholesky(dynamics.x0_cov).T
    )
    xs, us = [], []
    for t in range(T):
        u = x @ policy.K[t].T + policy.k[t] + torch.randn(N, dU, generator=g, dtype=DT) @ L[t].T
        xs.append(x)
        us.append(u)
        if t < T - 1:
            noise = torch.randn(N, dX, generator=g, dtype=DT) @ L_dyn[t].T
            x = torch.cat([x, u], -1) @ dynamics.F[t].T + dynamics.f[t] + noise
    return torch.stack(xs, 1), torch.stack(us, 1)


def test_kl_matches_monte_carlo() -> None:
    g = torch.Generator().manual_seed(0)
    T, dX, dU, N = 4, 3, 2, 200_000
    p, p_bar = _controller(T, dX, dU, g), _controller(T, dX, dU, g)
    mu_x = torch.randn(T, dX, generator=g, dtype=DT)
    sigma_x = _spd(dX, T, g=g, scale=0.5)
    kl = kl_divergence(p, p_bar, mu_x, sigma_x)
    x = (
        mu_x
        + (torch.linalg.cholesky(sigma_x) @ torch.randn(N, T, dX, 1, generator=g, dtype=DT))[..., 0]
    )
    u = p.mean_action(x) + (p.chol() @ torch.randn(N, T, dU, 1, generator=g, dtype=DT))[..., 0]
    samples = _log_density(p, x, u) - _log_density(p_bar, x, u)  # [N, T]
    standard_error = samples.std(0) / N**0.5
    assert bool((kl > 0).all())
    assert bool(((samples.mean(0) - kl).abs() < 4 * standard_error).all())


def test_kl_of_identical_controllers_is_zero() -> None:
    g = torch.Generator().manual_seed(1)
    p = _controller(5, 3, 2, g)
    kl = kl_divergence(p, p, torch.randn(5, 3, dtype=DT), _spd(3, 5, g=g))
    torch.testing.assert_close(kl, torch.zeros(5, dtype=DT), rtol=0.0, atol=1e-12)


def test_forward_pass_and_expected_cost_match_monte_carlo() -> None:
    g = torch.Generator().manual_seed(2)
    T, dX, dU, N = 5, 3, 2, 200_000
    policy, dynamics = _controller(T, dX, dU, g), _system(T, dX, dU, g)
    mu, sigma = forward_pass(policy, dynamics)
    x, u = _rollouts(policy, dynamics, N, g)
    y = torch.cat([x, u], -1)  # [N, T, dY]
    centred = y - y.mean(0)
    sample_sigma = torch.einsum("nti,ntj->tij", centred, centred) / (N - 1)
    scale = torch.diagonal(sigma, dim1=-2, dim2=-1).sqrt()  # [T, dY]
    assert bool(((y.mean(0) - mu).abs() < 5 * scale / N**0.5).all())
    corr_error = (sample_sigma - sigma) / (scale[:, :, None] * scale[:, None, :])
    assert float(corr_error.abs().max()) < 5 * (2 / N) ** 0.5
    cost = QuadraticCost(
        C=_spd(dX + dU, T, g=g),
        c=torch.randn(T, dX + dU, generator=g, dtype=DT),
        cc=torch.randn(T, generator=g, dtype=DT),
    )
    samples = 0.5 * torch.einsum("nti,tij,ntj->nt", y, cost.C, y) + (y * cost.c).sum(-1) + cost.cc
    standard_error = samples.std(0) / N**0.5
    assert bool(
        ((samples.mean(0) - expected_cost(cost, mu, sigma)).abs() < 5 * standard_error).all()
    )


def test_batched_marginals_and_trajectory_kl() -> None:
    g = torch.Generator().manual_seed(3)
    T, dX, dU = 6, 4, 2
    dynamics, p_bar = _system(T, dX, dU, g), _controller(T, dX, dU, g)
    batch = [_controller(T, dX, dU, g) for _ in range(3)]
    stacked = LinearGaussian(*(torch.stack(parts) for parts in zip(*batch, strict=True)))
    mu_x, sigma_x = state_marginals(stacked, dynamics)
    kl = trajectory_kl(stacked, p_bar, dynamics)
    for i, policy in enumerate(batch):
        mu, sigma = forward_pass(policy, dynamics)
        torch.testing.assert_close(mu_x[i], mu[:, :dX])
        torch.testing.assert_close(sigma_x[i], sigma[:, :dX, :dX])
        torch.testing.assert_close(kl[i], kl_divergence(policy, p_bar, mu, sigma))


def test_mix_is_linear_and_differentiable() -> None:
    g = torch.Generator().manual_seed(4)
    p_pre, p_cur = _controller(3, 2, 2, g), _controller(3, 2, 2, g)
    for got, want in zip(mix(p_pre, p_cur, 1.0), p_pre, strict=True):
        torch.testing.assert_close(got, want)
    for got, want in zip(mix(p_pre, p_cur, 0.0), p_cur, strict=True):
        torch.testing.assert_close(got, want)

    def mixed(alpha: Tensor, K_pre: Tensor, k_cur: Tensor, cov_cur: Tensor) -> Tensor:
        p_act = mix(p_pre._replace(K=K_pre), p_cur._replace(k=k_cur, cov=cov_cur), alpha)
        return torch.cat([part.flatten() for part in p_act])

    inputs = (torch.tensor(0.3, dtype=DT), p_pre.K, p_cur.k, p_cur.cov)
    assert torch.autograd.gradcheck(mixed, tuple(t.clone().requires_grad_() for t in inputs))


def test_hold_controller() -> None:
    T, n = 4, 3
    dX = 2 * n + 4
    q0 = torch.tensor([0.1, -0.2, 0.3], dtype=DT)
    kp, kd = torch.tensor([10.0, 20.0, 30.0], dtype=DT), torch.tensor([1.0, 2.0, 3.0], dtype=DT)
    variance = torch.tensor([0.5, 1.0, 2.0], dtype=DT)
    q_index, qd_index = slice(0, n), slice(n, 2 * n)
    policy = hold_controller(T, dX, q_index, qd_index, q0, kp, kd, variance)
    x = torch.randn(7, T, dX, generator=torch.Generator().manual_seed(5), dtype=DT)
    expected = -kp * (x[..., q_index] - q0) - kd * x[..., qd_index]
    torch.testing.assert_close(policy.mean_action(x), expected)
    torch.testing.assert_close(policy.cov, torch.diag(variance).expand(T, n, n))
    with pytest.raises(LolgpsError, match="q_index"):
        hold_controller(T, dX, slice(0, n + 1), qd_index, q0, kp, kd, variance)


def test_smoothed_noise_has_unit_variance_and_correlation() -> None:
    N, T, dU = 6000, 40, 3
    noise = smoothed_noise(N, T, dU, generator=torch.Generator().manual_seed(6))
    assert noise.shape == (N, T, dU) and noise.dtype == DT
    assert float((noise.var(0) - 1.0).abs().max()) < 0.12
    lag1 = (noise[:, 1:] * noise[:, :-1]).mean(0)  # [T-1, dU], unit variance entries
    assert float(lag1.min()) > 0.8
    again = smoothed_noise(N, T, dU, generator=torch.Generator().manual_seed(6))
    torch.testing.assert_close(noise, again)
    white = smoothed_noise(N, T, dU, sigma_steps=0.0, generator=torch.Generator().manual_seed(7))
    assert float((white[:, 1:] * white[:, :-1]).mean(0).abs().max()) < 0.1
