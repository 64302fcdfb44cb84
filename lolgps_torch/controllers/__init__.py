"""Linear-Gaussian controllers: construction, mixing, exploration noise, marginals, KL, cost."""

from lolgps_torch.controllers.linear_gaussian import hold_controller, mix
from lolgps_torch.controllers.marginals import (
    expected_cost,
    forward_pass,
    joint_marginals,
    kl_divergence,
    state_marginals,
    trajectory_kl,
)
from lolgps_torch.controllers.noise import smoothed_noise, smoothing_matrix

__all__ = [
    "expected_cost",
    "forward_pass",
    "hold_controller",
    "joint_marginals",
    "kl_divergence",
    "mix",
    "smoothed_noise",
    "smoothing_matrix",
    "state_marginals",
    "trajectory_kl",
]
