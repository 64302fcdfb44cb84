"""The global policy as the simulator's acting controller."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from lolgps_torch.policy.guard import guarded
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.sim.rollout import Actor, matmul_rows
from lolgps_torch.state import StateLayout


@dataclass
class PolicyActor:
    """``u_t = mu_theta(x_t) + shifted_t`` for the batch's rows ``rows`` (no noise when
    ``shifted`` is None), through the policy's guard (:func:`guarded`), which remembers per
    row whether its brake has tripped in this rollout (``tripped``, grown to the rows seen,
    reset at t = 0); plain data, so that it can be sent to a worker process. ``by_rows``: the
    row-wise form (:meth:`rowwise`)."""

    policy: GaussianPolicy
    shifted: Tensor | None  # [N, T, dU]: chol(Sigma_pi) eps_t per rollout
    tripped: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))
    by_rows: bool = False

    def rowwise(self) -> Actor:
        """The same actor computing each row alone (every matrix product of the policy and of
        the guard's brake by :func:`matmul_rows`), for rows stepped together."""
        return replace(self, tripped=torch.zeros(0, dtype=torch.bool), by_rows=True)

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        with torch.no_grad():
            u = self.policy(x, matmul_rows) if self.by_rows else self.policy(x)
        u = u if self.shifted is None else u + self.shifted[rows, t]
        start, stop = rows.start or 0, rows.stop
        if stop > self.tripped.shape[0]:
            grown = torch.zeros(stop, dtype=torch.bool, device=x.device)
            grown[: self.tripped.shape[0]] = self.tripped
            self.tripped = grown
        before = self.tripped[start:stop] & (t > 0)
        qd = x[..., StateLayout(self.policy.dU).qd]
        if self.by_rows:
            u, self.tripped[start:stop] = guarded(u, qd, self.policy.guard, before, t, matmul_rows)
        else:
            u, self.tripped[start:stop] = guarded(u, qd, self.policy.guard, before, t)
        return u


def policy_actor(policy: GaussianPolicy, noise: Tensor | None = None) -> Actor:
    """The global policy: its mean action, plus ``chol(Sigma_pi) eps_t`` when given noise
    ``eps: [N, T, dU]``, through its guard."""
    if noise is None:
        return PolicyActor(policy, None)
    L = torch.linalg.cholesky(policy.covariance()).detach()
    return PolicyActor(policy, noise @ L.T)
