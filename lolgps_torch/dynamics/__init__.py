"""Dynamics fitting (docs/ALGORITHM.md section 4): GMM, normal-inverse-Wishart prior, per-step fit."""

from lolgps_torch.dynamics.fit import (
    DynamicsConfig,
    DynamicsFitter,
    gaussian_regression,
    prior_from_config,
)
from lolgps_torch.dynamics.gmm import GaussianMixture
from lolgps_torch.dynamics.prior import GMMPrior, NIWPrior

__all__ = [
    "DynamicsConfig",
    "DynamicsFitter",
    "GMMPrior",
    "GaussianMixture",
    "NIWPrior",
    "gaussian_regression",
    "prior_from_config",
]
