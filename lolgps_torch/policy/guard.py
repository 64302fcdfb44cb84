"""The global policy's guard: bounds learnt from D_g, and braking where the policy leaves them.

Away from its data a ReLU policy extrapolates, and with a gain head it can ask for hundreds of
times the largest torque its teachers ever gave, flinging the arm a metre or more. The guard
keeps the policy inside what its teachers did, with bounds fitted to every condition's D_g:

    u_t = clip(mu_theta(x_t) (+ noise), -tau, tau)      tau_j = torque_margin max |mu_cur,j|
    while |q-dot_j(t)| > v_j(t) for some joint, or d_t - min_{s <= t} d_s > rho:
        u_t = clip(-beta M(q_t) q-dot_t / dt, -tau, tau)
    v_j(t) = min(speed_margin max_{m, s >= t - w} |q-dot_j^m(s)|, limit_j)
    rho = retreat_margin + max_{m, t} (d^m_t - min_{s <= t} d^m_s)

(limit_j a share of joint j's velocity limit, so that the brake acts before the arm's own
controller stops the arm; tau_j infinite unless a torque margin is given: the bound cost reaches to far holes and kept
the brake from stopping a flung arm; d_t = |p_tip - p*_tip| the tip's distance from its
target). The trip speed at step t is the largest speed D_g still reaches from ``w`` steps
before t on (``w`` None: one speed for every step, the largest in D_g): while the arm moves in
it is the teachers' largest, and once they have slowed down to insert, theirs from then on. A
policy that misses a far hole comes to rest at the plate and is flung from there, long after
it passed the largest speeds its teachers reached while moving in. The brake acts only while a
speed is past its bound: a policy that heads for a far hole faster than its teachers did is
slowed down, not stopped where it is (stopped, it would hang in the air, further from the hole
than it started). The retreat rho stops what the speeds miss, a slow rise away from the hole
late in the rollout: the teachers seldom move the tip away from their closest approach (on the
KUKA by 6-16 mm at most), and the brake then holds for as long as the tip stays away.

with ``M(q)`` the mass matrix of the arm's URDF model at the current pose and dt the control
step: the brake takes ``beta`` of the joint speeds away per control step, coupling included,
wherever the arm is, so the arm stops where it left the speeds its teachers used. (A brake
fitted to D_g's transitions, ``q-dot_{t+1} - q-dot_t ~ B u_t + c`` by least squares, with
``-beta B^-1`` in place of ``-beta M(q) / dt``, matched the arm only near the data: by the
model, its step multiplied the speeds by up to 4.3 at the Panda's mean pose in D_g and by more
than 8 at 90-100 % of poses within the joint limits, so it flung what it should have stopped;
``brake_gain.py``, a script since removed; see commit 9d82b2d.)
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.state import StateLayout


class Guard(NamedTuple):
    """Torque bounds ``tau [dU]``, the speeds ``v [S, dU]`` that trip the brake (row ``t`` at
    step ``t``, the last row from there on: ``S = 1`` is one speed for every step), the share
    ``beta`` of the joint speeds the brake takes away per control step (0-d; 0: none), the
    tip's retreat ``rho`` (m, 0-d; inf: none) that trips it, and ``hover = (h, tau_h)``
    ``[2]``: the brake steers the peg to h (m) above its target at 1/tau_h of the distance per
    second until the tip is within ``HOVER_RELEASE`` of that point (NaN: it stops the arm
    where it is; module docstring)."""

    torque: Tensor
    speed: Tensor
    brake: Tensor
    retreat: Tensor
    hover: Tensor

    @classmethod
    def off(cls, dU: int, device: torch.device | str = "cpu") -> Guard:
        """A guard that never acts: unbounded torques and speeds."""
        inf = torch.full((dU,), float("inf"), dtype=torch.float64, device=device)
        nan = torch.full((2,), float("nan"), dtype=torch.float64, device=device)
        return cls(inf, inf[None].clone(), torch.zeros_like(inf[0]), inf[0].clone(), nan)

    def speed_at(self, t: int) -> Tensor:
        """The trip speeds at step ``t``, ``[dU]``."""
        return self.speed[min(t, self.speed.shape[0] - 1)]


def fit_guard(
    x: Tensor,
    mean_cur: Tensor,
    layout: StateLayout,
    torque_margin: float | None,
    speed_margin: float,
    window: int | None,
    retreat_margin: float | None,
    beta: float,
    hover: tuple[float, float] | None = None,
    limit: Tensor | None = None,
) -> Guard:
    """The guard of rollouts with states ``x: [M, T+1, dX]`` (``x_T`` the state after the last
    action; its blocks as ``layout`` says) and teacher means ``mean_cur: [M, T, dU]`` (M >= 1),
    braking ``beta`` of the speeds away per step; ``torque_margin`` None leaves torques unbounded;
    ``window`` the steps before t from which on D_g's largest speed sets step t's trip speed
    (None: over every step); ``retreat_margin`` None: no retreat trips the brake; ``hover``
    (h, tau_h) steers the braked arm above its target (None: stops it); ``limit [dU]`` the
    highest trip speed of each joint (None: D_g's alone)."""
    if x.shape[0] == 0:
        raise LolgpsError("the policy's guard needs at least one rollout")
    speeds = x[..., layout.qd]  # [M, T+1, n]
    largest = mean_cur.abs().flatten(0, 1).amax(0)
    torque = (
        torch.full_like(largest, math.inf) if torque_margin is None else torque_margin * largest
    )
    per_step = speeds.abs().amax(0)  # [T+1, n]
    if window is None:
        envelope = per_step.amax(0, keepdim=True)
    else:
        onward = per_step.flip(0).cummax(0).values.flip(0)  # max over s >= t
        start = (torch.arange(per_step.shape[0]) - window).clamp(min=0)
        envelope = onward[start]  # max over s >= t - window, [T+1, n]
    distance = tip_distance(x, layout)  # [M, T+1]
    retreat = (distance - distance.cummin(1).values).amax()
    retreat = retreat + (math.inf if retreat_margin is None else retreat_margin)
    above = torque.new_tensor([math.nan, math.nan] if hover is None else hover)
    trip = speed_margin * envelope
    if limit is not None:
        trip = torch.minimum(trip, limit.to(trip))
    return Guard(torque, trip, torch.tensor(beta).to(torque), retreat, above)


def tip_distance(x: Tensor, layout: StateLayout) -> Tensor:
    """``d = |p_tip - p*_tip|`` of states ``x: [..., dX]`` -> ``[...]``."""
    tip = layout.points.start
    return torch.linalg.vector_norm(x[..., tip : tip + 3], dim=-1)


HOVER_RELEASE = 0.02  # m: the steered tip hands back to the policy this near its hover point


class Stopping(Protocol):
    """The arm model's braking torque at states ``x [n, dX]``: ``M(q) q-dot / dt``, or with
    ``hover = (h, tau_h)`` ``M(q) (q-dot - v) / dt``, v steering the peg to h above its target
    (:meth:`lolgps_torch.sim.model.ControlStep.stopping`)."""

    def __call__(self, x: Tensor, hover: Tensor | None = None) -> Tensor: ...


def guarded(
    u: Tensor,
    x: Tensor,
    layout: StateLayout,
    closest: Tensor,
    steering: Tensor,
    guard: Guard,
    t: int,
    stopping: Stopping,
) -> tuple[Tensor, Tensor, Tensor]:
    """Actions ``u: [n, dU]`` at step ``t`` and states ``x: [n, dX]`` (blocks as ``layout``)
    through the guard, given each rollout's closest approach to its target before ``t``
    (``closest [n]``, m; inf at the start) and whether its brake is steering it to the hover
    point (``steering [n]``, bool); returns the actions, the closest approach up to ``t`` and
    the steering after ``t``. ``stopping`` gives the brake's torque (:class:`Stopping`,
    evaluated only where a row brakes). A row brakes while a bound is passed. With the guard's
    hover, a row whose tip retreats past the bound while further from its target than the
    hover point h above it is steered there instead, and goes on being steered until its tip
    is within :data:`HOVER_RELEASE` of that point (or nearer its target than h); a row that
    only passes a speed, or is nearer its target than h, is stopped where it is, as without
    the hover (a reach that is too fast is slowed, then goes on; a peg at the mouth or in the
    hole is never pulled out)."""
    qd, distance = x[..., layout.qd], tip_distance(x, layout)
    closest = torch.minimum(closest, distance)
    retreating = distance - closest > guard.retreat
    braking = (qd.abs() > guard.speed_at(t)).any(-1) | retreating
    held = u
    tip = x[..., layout.points.start : layout.points.start + 3].clone()
    tip[..., 2] -= guard.hover[0]
    # further from the target than the hover point is (never without the hover: h is NaN)
    above = distance > guard.hover[0]
    away = torch.linalg.vector_norm(tip, dim=-1) > HOVER_RELEASE
    steered = (retreating | (steering & away)) & above
    stopped = braking & ~steered
    if bool(steered.any() or stopped.any()):
        held = u.clone()
        if bool(steered.any()):
            held[steered] = -guard.brake * stopping(x[steered], guard.hover)
        if bool(stopped.any()):
            held[stopped] = -guard.brake * stopping(x[stopped])
    return torch.maximum(torch.minimum(held, guard.torque), -guard.torque), closest, steered


APPROACH_STEPS = 3  # a joint nears its position bound no faster than it would reach it in 3 steps


class ArmBrake(Protocol):
    """The limits the guard keeps the arm within, and the arm model it brakes and predicts the
    arm by (:class:`lolgps_torch.sim.model.ControlStep`): the URDF's velocity limits and
    position limits ``[dU]`` (-inf and inf where a joint has none), the control step ``dt``
    (s), the brake's torque (:class:`Stopping`) and the mass matrices ``M(q)`` of states
    ``x: [n, dX]`` (``[n, dU, dU]``, each row computed alone)."""

    velocity: Tensor
    lower: Tensor
    upper: Tensor
    dt: float

    def stopping(self, x: Tensor, hover: Tensor | None = None) -> Tensor: ...

    def mass_matrix(self, x: Tensor) -> Tensor: ...


def within_limits(
    u: Tensor,
    x: Tensor,
    layout: StateLayout,
    arm: ArmBrake,
    inertia: Tensor,
    share: float,
    margin: float,
) -> Tensor:
    """Actions ``u: [n, dU]`` at states ``x: [n, dX]`` (blocks as ``layout``) changed so that
    the arm model's joint speeds after the step keep within the arm's limits, with ``inertia``
    the rows' mass matrices ``M(q)`` (``[n, dU, dU]``):

        q-dot'(a) = q-dot + a dt M(q)^-1 u,   a = max {a in [0, 1]: lo <= q-dot'(a) <= hi}
        hi_j = min(s v_j, (upper_j - m_j - q_j) / (k dt)),  lo_j = max(-s v_j, (lower_j + m_j - q_j) / (k dt))

    (v the velocity limits, s = ``share``, ``m_j = min(margin, (upper_j - lower_j) / 4)`` (rad)
    inside the position limits, k = :data:`APPROACH_STEPS`): the action is shortened along its
    own direction until no joint would pass the share of its velocity limit, or approach its
    bound m inside a position limit faster than it would reach it in k steps. Where no share
    of it will do (a joint coasts towards a bound, or is past one and must move back), the
    action is the torque ``M(q) (clip(w, lo, hi) - q-dot) / dt``: with w the speeds the action
    would give, ``q-dot'(1)``, each clipped to its bounds, or, once a joint is past its
    position bound, w = 0: the whole arm stops, that joint moving back. The speed is checked
    at the end of the step, where a torque held from rest is fastest; the model leaves out
    gravity (the arm compensates it), Coriolis forces, damping, contact and a command delay,
    which the share's headroom and the margin absorb. Each row is computed alone."""
    q, qd = x[..., layout.q], x[..., layout.qd]
    cap = share * arm.velocity
    inside = torch.minimum(torch.full_like(arm.upper, margin), (arm.upper - arm.lower) / 4)
    ahead = APPROACH_STEPS * arm.dt
    hi = torch.minimum(cap, (arm.upper - inside - q) / ahead)
    lo = torch.maximum(-cap, (arm.lower + inside - q) / ahead)
    change = arm.dt * torch.stack(
        [torch.linalg.solve(m, a) for m, a in zip(inertia, u, strict=True)]
    )
    after = qd + change
    outside = ((after < lo) | (after > hi)).any(-1)
    if not bool(outside.any()):
        return u
    s, c, lo, hi = qd[outside], change[outside], lo[outside], hi[outside]
    moving = c != 0
    safe = torch.where(moving, c, torch.ones_like(c))
    ends = torch.stack([(lo - s) / safe, (hi - s) / safe])
    still = (s >= lo) & (s <= hi)  # a joint the action does not move: any a, or none
    first = torch.where(moving, ends.amin(0), torch.where(still, -math.inf, math.inf))
    last = torch.where(moving, ends.amax(0), torch.where(still, math.inf, -math.inf))
    a_lo, a_hi = first.amax(-1).clamp(min=0.0), last.amin(-1).clamp(max=1.0)
    feasible = a_lo <= a_hi
    held = u.clone()
    rows = outside.nonzero().squeeze(-1)
    held[rows[feasible]] = a_hi[feasible, None] * u[rows[feasible]]
    if not bool(feasible.all()):
        stuck = rows[~feasible]
        # past a position bound the whole arm stops, the joint moving back (contact, which the
        # model leaves out, pushes a joint there while the action goes on); else every joint
        # keeps the action's speed, clipped
        past = ((q[stuck] > arm.upper - inside) | (q[stuck] < arm.lower + inside)).any(-1)
        wanted = torch.where(past[:, None], torch.zeros_like(after[stuck]), after[stuck])
        clipped = torch.maximum(torch.minimum(wanted, hi[~feasible]), lo[~feasible])
        back = clipped - s[~feasible]
        held[stuck] = (
            torch.stack([m @ b for m, b in zip(inertia[stuck], back, strict=True)]) / arm.dt
        )
    return held
