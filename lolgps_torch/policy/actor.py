"""The global policy as the simulator's acting controller."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from lolgps_torch.policy.guard import guarded, tip_distance
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.sim.rollout import Actor
from lolgps_torch.state import StateLayout


@dataclass
class PolicyActor:
    """``u_t = mu_theta(x_t) + shifted_t`` for the batch's rows ``rows`` (no noise when
    ``shifted`` is None), through the policy's guard (:func:`guarded`), which remembers per
    row whether its brake has tripped in this rollout (``tripped``) and the nearest its tip has
    come to the target (``nearest``), both grown to the rows seen and reset at t = 0; plain
    data, so that it can be sent to a worker process."""

    policy: GaussianPolicy
    shifted: Tensor | None  # [N, T, dU]: chol(Sigma_pi) eps_t per rollout
    tripped: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))
    nearest: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.float64))

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        with torch.no_grad():
            u = self.policy(x)
        u = u if self.shifted is None else u + self.shifted[rows, t]
        start, stop = rows.start or 0, rows.stop
        if stop > self.tripped.shape[0]:
            self.tripped = _grown(self.tripped, stop, False)
            self.nearest = _grown(self.nearest, stop, math.inf)
        layout = StateLayout(self.policy.dU)
        distance = tip_distance(x, layout)
        if t > 0:
            self.nearest[start:stop] = torch.minimum(self.nearest[start:stop], distance)
        else:
            self.nearest[start:stop] = distance
        before = self.tripped[start:stop] & (t > 0)
        retreated = distance - self.nearest[start:stop]
        u, self.tripped[start:stop] = guarded(
            u, x[..., layout.qd], retreated, self.policy.guard, before
        )
        return u


def _grown(values: Tensor, size: int, fill: float | bool) -> Tensor:
    """``values: [m]`` extended to ``[size]`` with ``fill``."""
    grown = torch.full((size,), fill, dtype=values.dtype, device=values.device)
    grown[: values.shape[0]] = values
    return grown


def policy_actor(policy: GaussianPolicy, noise: Tensor | None = None) -> Actor:
    """The global policy: its mean action, plus ``chol(Sigma_pi) eps_t`` when given noise
    ``eps: [N, T, dU]``, through its guard."""
    if noise is None:
        return PolicyActor(policy, None)
    L = torch.linalg.cholesky(policy.covariance()).detach()
    return PolicyActor(policy, noise @ L.T)
