"""The model prior of the per-step dynamics fit: a linear "arm" whose true dynamics is known."""

from __future__ import annotations

import pytest
import torch

from lolgps_torch.dynamics import DynamicsConfig, DynamicsFitter
from lolgps_torch.dynamics.model_prior import ModelPrior
from lolgps_torch.errors import LolgpsError

dX, dU, T = 6, 2, 8


def _system(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(dX, dtype=torch.float64) + 0.1 * torch.randn(dX, dX + dU, generator=g,
                                                                 dtype=torch.float64)[:, :dX]  # fmt: skip
    B = torch.randn(dX, dU, generator=g, dtype=torch.float64)
    return torch.cat([A, B], 1), torch.randn(dX, generator=g, dtype=torch.float64)


def _samples(F: torch.Tensor, f: torch.Tensor, N: int, seed: int) -> tuple[torch.Tensor, ...]:
    """N rollouts of ``x' = F [x; u] + f`` with random actions, ``x: [N, T, dX]``."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(N, T, dX, dtype=torch.float64)
    x[:, 0] = torch.randn(N, dX, generator=g, dtype=torch.float64)
    u = torch.randn(N, T, dU, generator=g, dtype=torch.float64)
    for t in range(T - 1):
        x[:, t + 1] = torch.cat([x[:, t], u[:, t]], -1) @ F.T + f
    return x, u


def _linearizer(F: torch.Tensor, f: torch.Tensor):
    def linearize(x: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return F.expand(x.shape[0], -1, -1), f.expand(x.shape[0], -1)

    return linearize


def test_exact_model_gives_its_dynamics_from_few_samples() -> None:
    """3 samples span 2 of the 8 directions of [x; u]: plain regression cannot recover the
    dynamics, the exact model's prior does (off the samples' span too)."""
    F, f = _system(0)
    x, u = _samples(F, f, N=3, seed=1)
    fit = DynamicsFitter(DynamicsConfig(use_prior=False, prior="model"), _linearizer(F, f))
    dyn = fit.update(x, u)
    torch.testing.assert_close(dyn.F, F.expand_as(dyn.F), rtol=0, atol=1e-4)
    torch.testing.assert_close(dyn.f, f.expand_as(dyn.f), rtol=0, atol=1e-4)
    assert fit.model_prior is not None and fit.model_prior.weights is not None
    assert bool((fit.model_prior.weights > 0.99).all())
    plain = DynamicsFitter(DynamicsConfig(use_prior=False, regression_reg=1e-6)).update(x, u)
    assert float((plain.F - F).abs().max()) > 0.1


def test_wrong_model_gives_way_to_the_data_prior() -> None:
    """Where the model does not predict the samples (another system: "contact"), its weight
    falls and the fit is that of the GMM prior."""
    F, f = _system(0)
    wrong_F, wrong_f = _system(2)
    x, u = _samples(F, f, N=20, seed=3)
    config = DynamicsConfig(prior="model", min_clusters=1, max_clusters=1)
    fit = DynamicsFitter(config, _linearizer(wrong_F, wrong_f))
    dyn = fit.update(x, u)
    assert fit.model_prior is not None and fit.model_prior.weights is not None
    assert float(fit.model_prior.weights.max()) < 0.05
    gmm = DynamicsFitter(DynamicsConfig(min_clusters=1, max_clusters=1)).update(x, u)
    torch.testing.assert_close(dyn.F, gmm.F, rtol=0, atol=0.05)


def test_model_prior_settings_are_checked() -> None:
    F, f = _system(0)
    with pytest.raises(LolgpsError):
        DynamicsConfig(prior="physics")  # type: ignore[arg-type]
    with pytest.raises(LolgpsError):
        DynamicsFitter(DynamicsConfig(prior="model"))
    with pytest.raises(LolgpsError):
        ModelPrior(_linearizer(F, f), tolerance=0.0)
