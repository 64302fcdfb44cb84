"""The global policy as the simulator's acting controller, and any actor kept within the
arm's limits."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from lolgps_torch.policy.guard import ArmBrake, Guard, guarded, within_limits
from lolgps_torch.policy.net import Acting, GaussianPolicy
from lolgps_torch.sim.rollout import Actor, Rowwise, linear_gaussian_actor, matmul_rows
from lolgps_torch.state import StateLayout
from lolgps_torch.types import LinearGaussian

#: rad: the guard's prediction reuses a rollout's mass matrix until a joint has moved this far
#: from the pose it was made at (the matrix changes by a few per cent; making it anew at every
#: step nearly tripled a policy rollout's time)
INERTIA_REUSE = 0.05


@dataclass
class PolicyActor:
    """``u_t = mu_theta(x_t) + shifted_t`` for the batch's rows ``rows`` (no noise when
    ``shifted`` is None), through the policy's brake (:func:`guarded`, by the arm's model
    ``arm``), which remembers per row the tip's closest approach to its target in this rollout
    (``closest``, m) and whether its brake steers it above the target (``steering``), both grown
    to the rows seen and forgotten at t = 0; plain data, so that it can be sent to a worker
    process. ``by_rows``: the row-wise form (:meth:`rowwise`). The policy's tensors, its guard
    and the state's layout are taken out of it once, when the actor is made (``acting``,
    ``guard``, ``layout``): a step evaluates the policy on one row, where looking them up took a
    quarter of its time."""

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
            self._grow(stop, x)
        if t == 0:
            self.closest[start:stop] = torch.inf
            self.steering[start:stop] = False
        u, self.closest[start:stop], self.steering[start:stop] = guarded(
            u, x, self.layout, self.closest[start:stop], self.steering[start:stop], self.guard,
            t, self.arm.stopping,
        )  # fmt: skip
        return u

    def _grow(self, stop: int, x: Tensor) -> None:
        """The per-row memories grown to ``stop`` rows."""
        kept = self.closest.shape[0]
        closest = torch.full((stop,), torch.inf, dtype=x.dtype, device=x.device)
        closest[:kept] = self.closest
        steering = torch.zeros(stop, dtype=torch.bool, device=x.device)
        steering[:kept] = self.steering
        self.closest, self.steering = closest, steering


@dataclass
class LimitedActor:
    """``inner``'s actions kept within the arm's limits by its model ``arm``
    (:func:`within_limits`: ``share`` of the velocity limits, ``margin`` rad inside the
    position limits), with each row's mass matrix ``M(q)`` kept from a recent pose
    (``inertia`` made at ``inertia_at``: anew where a joint has moved more than
    :data:`INERTIA_REUSE` from that pose, and at t = 0), grown to the rows seen; plain data,
    so that it can be sent to a worker process. Any actor can be limited: the global policy's
    (:func:`policy_actor`) and the local controllers' samples."""

    inner: Actor
    arm: ArmBrake
    share: float
    margin: float
    inertia: Tensor = field(default_factory=lambda: torch.zeros(0, 0, 0, dtype=torch.float64))
    inertia_at: Tensor = field(default_factory=lambda: torch.zeros(0, 0, dtype=torch.float64))

    def rowwise(self) -> Actor:
        """The same actor computing each row alone: ``inner``'s row-wise form (the limits are
        row by row already)."""
        if not isinstance(self.inner, Rowwise):
            raise TypeError(f"{type(self.inner).__name__} has no row-wise form")
        return LimitedActor(self.inner.rowwise(), self.arm, self.share, self.margin)

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        u = self.inner(t, x, rows)
        start, stop = rows.start or 0, rows.stop
        if stop > self.inertia.shape[0]:
            self._grow(stop, x)
        if t == 0:
            self.inertia_at[start:stop] = torch.nan
        layout = StateLayout(u.shape[-1])
        inertia = self._inertia(x, layout, start, stop)
        return within_limits(u, x, layout, self.arm, inertia, self.share, self.margin)

    def _grow(self, stop: int, x: Tensor) -> None:
        """The per-row mass matrices grown to ``stop`` rows."""
        dU, kept = self.arm.velocity.shape[0], self.inertia.shape[0]
        inertia = torch.zeros(stop, dU, dU, dtype=x.dtype, device=x.device)
        at = torch.full((stop, dU), torch.nan, dtype=x.dtype, device=x.device)
        if kept:
            inertia[:kept], at[:kept] = self.inertia, self.inertia_at
        self.inertia, self.inertia_at = inertia, at

    def _inertia(self, x: Tensor, layout: StateLayout, start: int, stop: int) -> Tensor:
        """The rows' mass matrices, made anew where a joint has moved more than
        :data:`INERTIA_REUSE` since they were made (or at t = 0)."""
        q = x[..., layout.q]
        moved = ~((q - self.inertia_at[start:stop]).abs().amax(-1) <= INERTIA_REUSE)
        if bool(moved.any()):
            index = torch.arange(start, stop, device=x.device)[moved]
            self.inertia[index] = self.arm.mass_matrix(x[moved])
            self.inertia_at[index] = q[moved]
        return self.inertia[start:stop]


def kept_within(actor: Actor, arm: ArmBrake, limits: tuple[float, float] | None) -> Actor:
    """``actor`` kept within the arm's limits by its model ``arm``, ``limits`` being
    ``(share, margin)`` (:class:`LimitedActor`; :meth:`PolicyConfig.limits`), or ``actor``
    itself with None."""
    return actor if limits is None else LimitedActor(actor, arm, *limits)


def controller_actor(
    p: LinearGaussian, noise: Tensor, arm: ArmBrake, limits: tuple[float, float] | None
) -> Actor:
    """The linear-Gaussian controller ``p`` with ``noise`` ``[N, T, dU]``
    (:func:`~lolgps_torch.sim.rollout.linear_gaussian_actor`) kept within ``limits``
    (:func:`kept_within`): every rollout of a local controller, its samples and its noiseless
    checks alike."""
    return kept_within(linear_gaussian_actor(p, noise), arm, limits)


def policy_actor(policy: GaussianPolicy, arm: ArmBrake, noise: Tensor | None = None) -> Actor:
    """The global policy: its mean action, plus ``chol(Sigma_pi) eps_t`` when given noise
    ``eps: [N, T, dU]``, through its guard, which brakes and keeps within the limits by the
    arm's model ``arm`` (:class:`~lolgps_torch.sim.model.ControlStep`)."""
    shifted = None
    if noise is not None:
        shifted = noise @ torch.linalg.cholesky(policy.covariance()).detach().T
    return kept_within(PolicyActor(policy, arm, shifted), arm, policy.config.limits())
