"""The global policy as the simulator's acting controller."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.sim.rollout import Actor


class PolicyActor(NamedTuple):
    """``u_t = mu_theta(x_t) + shifted_t`` for the batch's rows ``rows`` (no noise when
    ``shifted`` is None); plain data, so that it can be sent to a worker process."""

    policy: GaussianPolicy
    shifted: Tensor | None  # [N, T, dU]: chol(Sigma_pi) eps_t per rollout

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        with torch.no_grad():
            u = self.policy(x)
        return u if self.shifted is None else u + self.shifted[rows, t]


def policy_actor(policy: GaussianPolicy, noise: Tensor | None = None) -> Actor:
    """The global policy: its mean action, plus ``chol(Sigma_pi) eps_t`` when given noise
    ``eps: [N, T, dU]``."""
    if noise is None:
        return PolicyActor(policy, None)
    L = torch.linalg.cholesky(policy.covariance()).detach()
    return PolicyActor(policy, noise @ L.T)
