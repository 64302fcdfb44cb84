"""The global policy as the simulator's acting controller."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from lolgps_torch.policy.guard import ArmBrake, Guard, guarded, within_limits
from lolgps_torch.policy.net import Acting, GaussianPolicy
from lolgps_torch.sim.rollout import Actor, matmul_rows
from lolgps_torch.state import StateLayout


@dataclass
class PolicyActor:
    """``u_t = mu_theta(x_t) + shifted_t`` for the batch's rows ``rows`` (no noise when
    ``shifted`` is None), through the policy's guard (:func:`guarded`, braking by the arm's
    model ``arm``, then :func:`within_limits` of the arm's limits), which remembers per row the tip's closest approach to its target in
    this rollout (``closest``, m) and whether its brake steers it above the target
    (``steering``), both grown to the rows seen and forgotten at t = 0; plain data, so
    that it can be sent to a worker process. ``by_rows``: the row-wise form
    (:meth:`rowwise`). The policy's tensors, its guard and the state's layout are taken out of
    it once, when the actor is made (``acting``, ``guard``, ``layout``): a step evaluates the
    policy on one row, where looking them up took a quarter of its time."""

    policy: GaussianPolicy
    arm: ArmBrake
    shifted: Tensor | None  # [N, T, dU]: chol(Sigma_pi) eps_t per rollout
    closest: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.float64))
    steering: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.bool))
    by_rows: bool = False
    acting: Acting = field(init=False, repr=False)
    guard: Guard = field(init=False, repr=False)
    layout: StateLayout = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.acting = self.policy.acting()
        self.guard = self.policy.guard
        self.layout = StateLayout(self.policy.dU)

    def rowwise(self) -> Actor:
        """The same actor computing each row alone (every matrix product of the policy by
        :func:`matmul_rows`; the brake is row by row already), for rows stepped together."""
        return replace(
            self,
            closest=torch.zeros(0, dtype=torch.float64),
            steering=torch.zeros(0, dtype=torch.bool),
            by_rows=True,
        )

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        with torch.no_grad():
            u = self.acting(x, matmul_rows if self.by_rows else None)
        u = u if self.shifted is None else u + self.shifted[rows, t]
        start, stop = rows.start or 0, rows.stop
        if stop > self.closest.shape[0]:
            grown = torch.full((stop,), torch.inf, dtype=x.dtype, device=x.device)
            grown[: self.closest.shape[0]] = self.closest
            self.closest = grown
            steering = torch.zeros(stop, dtype=torch.bool, device=x.device)
            steering[: self.steering.shape[0]] = self.steering
            self.steering = steering
        if t == 0:
            self.closest[start:stop] = torch.inf
            self.steering[start:stop] = False
        u, self.closest[start:stop], self.steering[start:stop] = guarded(
            u, x, self.layout, self.closest[start:stop], self.steering[start:stop], self.guard,
            t, self.arm.stopping,
        )  # fmt: skip
        config = self.policy.config
        if not config.guard:
            return u
        return within_limits(u, x, self.layout, self.arm, config.guard_limit, config.guard_position)


def policy_actor(policy: GaussianPolicy, arm: ArmBrake, noise: Tensor | None = None) -> Actor:
    """The global policy: its mean action, plus ``chol(Sigma_pi) eps_t`` when given noise
    ``eps: [N, T, dU]``, through its guard, which brakes and keeps within the limits by the
    arm's model ``arm`` (:class:`~lolgps_torch.sim.model.ControlStep`)."""
    if noise is None:
        return PolicyActor(policy, arm, None)
    L = torch.linalg.cholesky(policy.covariance()).detach()
    return PolicyActor(policy, arm, noise @ L.T)
