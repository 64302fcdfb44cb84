"""The global policy as the simulator's acting controller."""

from __future__ import annotations

import torch
from torch import Tensor

from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.sim.rollout import Actor


def policy_actor(policy: GaussianPolicy, noise: Tensor | None = None) -> Actor:
    """The global policy: its mean action, plus ``chol(Sigma_pi) eps_t`` when given noise
    ``eps: [N, T, dU]``."""
    L = torch.linalg.cholesky(policy.covariance()).detach()

    def act(t: int, x: Tensor, rows: slice) -> Tensor:
        with torch.no_grad():
            u = policy(x)
        return u if noise is None else u + noise[rows, t] @ L.T

    return act
