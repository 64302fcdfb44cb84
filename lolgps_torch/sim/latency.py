"""The arm's command delay, found from how it answers random commands (no plant setting read).

Excitation: ``rollouts`` rollouts of ``steps`` control steps from rest at the start pose q0,
each command drawn anew every control step, ``u_t ~ N(0, diag(sigma^2))`` on top of the
arm's own gravity compensation, with ``sigma_j = a I_j / dt`` (``I_j`` joint j's effective
inertia at q0 in the URDF's arm): each command changes a joint's speed by about ``a`` rad/s.
The commands come from their own generator (``DelayConfig.seed``), so the learner's random
streams are untouched. The rollouts are short, so that the arm stays near q0, where the fit
below is linear, also when the compensation misses a load: with 8 rollouts of 40 steps a
payload of 0.5 kg that the URDF lacks, compensated by the URDF alone, sagged the arm far enough
to hide any delay (``delay_estimate.py``, a script since removed, at commit 9d82b2d;
``docs/RESULTS.md`` at c902895, section 8).

Fit: a delay of ``d = k H + r`` physics steps (``H`` per control step, ``0 <= r < H``) lets
command ``u_{t-k}`` act for the last ``H - r`` physics steps of control step t and
``u_{t-k-1}`` for the first r, so the joint speeds change over the step by the impulse of

    v_t(d) = ((H - r) u_{t-k} + r u_{t-k-1}) / H        (u_s = 0 for s < 0)

For every candidate d in 0..D the least-squares fit

    qd_{t+1} - qd_t = B v_t(d) + A [s_t, 1]       (B, A free matrices)

leaves a residual sum of squares RSS(d); the estimate is the d with the smallest one, unless
every RSS(d) lies within :data:`EXPLAINED` times the smallest: then the commands explain the
speeds equally badly at every delay (an arm whose response the excitation does not show), and
the estimate is no delay.

The state ``s_t`` is not the observed ``[q_t, qd_t]``, whose sensor noise also enters
``qd_{t+1} - qd_t`` and biased the estimate a physics step late (the KUKA with 1 mrad: 10 ms
where there was none). It is its least-squares prediction from what decides it without noise,
the step t and every earlier command ``u_0 .. u_{t-1}`` of the rollout (an instrumental
variable: all rollouts start at rest at q0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from lolgps_torch.errors import LolgpsError
from lolgps_torch.sim.simulator import World

# the least ratio of the largest RSS(d) to the smallest for which a delay is estimated: where
# the fit explains the excitation, a delay far off leaves thousands of times the residual
# (example-robot-data's Talos left arm, without delay: 2 600); where it does not (the full
# Talos from its torso) every delay's residual was within 1.017 times the smallest
EXPLAINED = 1.25


@dataclass(frozen=True)
class DelayConfig:
    """Settings of the delay's estimate (module docstring).

    :param rollouts: excitation rollouts from the start pose.
    :param steps: control steps per excitation rollout.
    :param speed: a: the joint-speed change (rad/s) a command's standard deviation makes in
        one control step.
    :param longest: D: the longest delay considered (s).
    :param seed: seed of the excitation's commands.
    """

    rollouts: int = 64
    steps: int = 5
    speed: float = 0.05
    longest: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rollouts < 1 or self.steps < 2:
            raise LolgpsError(
                f"delay estimate: rollouts >= 1 and steps >= 2 needed, got {self.rollouts}, "
                f"{self.steps}"
            )
        for name, value in (("speed", self.speed), ("longest", self.longest)):
            if not (math.isfinite(value) and value > 0.0):
                raise LolgpsError(f"delay estimate: {name} must be positive, got {value}")
        if self.seed < 0:
            raise LolgpsError(f"delay estimate: seed must be >= 0, got {self.seed}")


class DelayEstimate(NamedTuple):
    """The estimated delay in physics steps and seconds, and ``RSS(d) / RSS(best)`` for
    every candidate d = 0..D physics steps (1 at the estimate)."""

    steps: int
    seconds: float
    relative_rss: tuple[float, ...]


class Excitation(NamedTuple):
    """Observed joint angles ``q: [R, S+1, n]`` and speeds ``qd: [R, S+1, n]``, and the
    commands issued ``u: [R, S, n]``."""

    q: np.ndarray
    qd: np.ndarray
    u: np.ndarray


def excite(world: World, q0: np.ndarray, config: DelayConfig) -> Excitation:
    """Run the excitation rollouts (module docstring) in ``world``, which must have its hole
    set; the commands' scale comes from the URDF's effective inertia at ``q0``."""
    n, dt = world.arm.dof, world.config.dt
    sigma = config.speed * world.effective_inertia(q0.tolist()).numpy() / dt
    rng = np.random.default_rng(config.seed)
    u = rng.normal(0.0, 1.0, (config.rollouts, config.steps, n)) * sigma
    rollouts = []
    for r in range(config.rollouts):
        states = [world.reset(q0, key=(r,))]
        states += [world.step(u[r, t]) for t in range(config.steps)]
        rollouts.append(np.stack(states))
    x = np.stack(rollouts)
    return Excitation(x[..., :n], x[..., n : 2 * n], u)


def impulse(u: np.ndarray, delay: int, substeps: int) -> np.ndarray:
    """``v_t(d)`` of the module docstring for commands ``u: [R, S, n]`` and a delay of
    ``delay`` physics steps of ``substeps`` per control step, ``[R, S, n]``."""
    k, r = divmod(delay, substeps)
    padded = np.concatenate([np.zeros_like(u[:, : k + 1]), u], axis=1)
    steps = u.shape[1]
    current = padded[:, 1 : steps + 1]  # u_{t-k}
    earlier = padded[:, :steps]  # u_{t-k-1}
    return ((substeps - r) * current + r * earlier) / substeps


def predicted_state(data: Excitation) -> np.ndarray:
    """``s_t`` of the module docstring, ``[R * S, 2n]``: the observed ``[q_t, qd_t]`` fitted by
    least squares on the step t (one indicator per step) and the rollout's earlier commands
    ``u_{t-1}, ..., u_0`` (zero before the first)."""
    R, S, n = data.u.shape
    earlier = [
        np.concatenate([np.zeros((R, lag, n)), data.u[:, : S - lag]], 1) for lag in range(1, S)
    ]
    step = np.broadcast_to(np.eye(S), (R, S, S))
    instruments = np.concatenate([step, *earlier], -1).reshape(R * S, -1)
    observed = np.concatenate([data.q[:, :-1], data.qd[:, :-1]], -1).reshape(R * S, -1)
    coef = np.linalg.lstsq(instruments, observed, rcond=None)[0]
    return instruments @ coef


def estimate_delay(data: Excitation, dt: float, substeps: int, longest: float) -> DelayEstimate:
    """The delay of the smallest residual of the fits of the module docstring, among 0..D
    physics steps of ``dt / substeps`` (D = ``longest`` in whole physics steps, rounded down);
    none where every residual is within :data:`EXPLAINED` times the smallest."""
    dqd = (data.qd[:, 1:] - data.qd[:, :-1]).reshape(-1, data.u.shape[-1])
    state = np.concatenate([predicted_state(data), np.ones((dqd.shape[0], 1))], -1)
    physics_step = dt / substeps
    candidates = range(int(math.floor(longest / physics_step + 1e-9)) + 1)
    rss = []
    for d in candidates:
        features = np.concatenate([impulse(data.u, d, substeps).reshape(dqd.shape), state], -1)
        coef = np.linalg.lstsq(features, dqd, rcond=None)[0]
        rss.append(float(((features @ coef - dqd) ** 2).sum()))
    best = int(np.argmin(rss))
    if max(rss) < EXPLAINED * rss[best]:
        best = 0
    floor = max(rss[best], 1e-300)
    return DelayEstimate(best, best * physics_step, tuple(v / floor for v in rss))
