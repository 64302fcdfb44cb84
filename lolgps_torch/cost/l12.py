"""The peg-insertion cost (paper eq. 9, docs/ALGORITHM.md section 2) and its quadratic expansion.

    l(x_t, u_t) = 1/2 sum_j wu_j u_j^2  +  1/2 sum_j wv_j e_j^2  +  m_t * l12(z_t),
    e_j = max(0, |q-dot_j| - s v_j),
    l12(z)      = 1/2 l2 |z|^2 + l1 sqrt(gamma + |z|^2),
    z_t         = A (p(q_t) - p*_t),     p*_t = p* + h_t e_z,   h_t = h_0 max(0, 1 - t / t_d),

where p(q) stacks the tip and top points (6), p* their targets, and A (8 x 6) holds
sqrt(per-axis point weights) on its first six rows and sqrt(tilt weight) times the lateral
offset between tip and top on the last two.  m_t is 1, or ``final_multiplier`` at t = T-1.
wu_j = action_weight / effort_j^2, so the action cost is in units of the effort limits, and
wv_j = speed_weight / v_j^2 (v_j the joint's velocity limit, s = ``speed_free``): a joint's
speed costs nothing up to the share s of its limit, and beyond it the excess, in units of the
limit, costs quadratically. It keeps the first commands from flinging the arm towards the
lifted target faster than its joints may move (docs/ALGORITHM.md section 2;
``scripts/research/speed_limits.py``) and leaves slower motion as it was. Its expansion is
exact at each sample: gradient ``wv_j e_j sign(q-dot_j)`` and curvature ``wv_j`` where
``e_j > 0``, both 0 elsewhere.

The descent schedule (h_0 = ``descent_height``, t_d = ``descent_steps``; off when either is
0) lifts both targets by h_t, so the optimal trajectory first aligns over the hole and
then lowers the peg at a steady rate instead of diving at it.  The state keeps p - p*.

The expansion is Gauss-Newton through forward kinematics (as the original GPS):
l_q = J^T A^T g, l_qq = J^T A^T H A J with g, H the gradient and Hessian of l12 in z.
The cost depends on x only through q.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.state import StateLayout
from lolgps_torch.types import QuadraticCost


@dataclass(frozen=True)
class CostConfig:
    """Weights of the l12 + action cost.

    :param l1: weight of the sqrt (l1-like) term. :param l2: weight of the squared term.
    :param gamma: smoothing of the sqrt term.
    :param lateral_weight: per-point weight on the x and y errors.
    :param vertical_weight: per-point weight on the z error.
    :param tilt_weight: weight on the lateral offset between tip and top (a tilted peg).
    :param final_multiplier: multiplier of the point term at the last step.
    :param action_weight: wu in units of the effort limits.
    :param descent_height: h_0, the height (m) the targets are lifted by at t = 0.
    :param descent_steps: t_d, the step at which the lifted targets reach p*. With 40 the
        lifted tip target reaches the mouth at step 20, before an arm within its velocity
        limits has finished coming over the hole: the global policy then arrived at the mouth
        up to 21 mm beside it (12 KUKA seeds, ``scripts/research/mouth.py``).
    :param speed_weight: wv in units of the velocity limits. Its curvature enters the
        teachers' precision wherever a joint passes the free share, along the approach: with
        10 that held 77-84 % of the S-step's weight in steps 0-9, and the policy was fitted
        loosely in the descent into the hole (``scripts/research/precision_share.py``).
    :param speed_free: s, the share of each joint's velocity limit below which speed is free.
    """

    l1: float = 0.1
    l2: float = 10.0
    gamma: float = 1e-5
    lateral_weight: float = 5.0
    vertical_weight: float = 1.0
    tilt_weight: float = 5.0
    final_multiplier: float = 10.0
    action_weight: float = 1.0
    descent_height: float = 0.2
    descent_steps: int = 60
    speed_weight: float = 1.0
    speed_free: float = 0.3

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_weight) and self.speed_weight >= 0.0):
            raise LolgpsError(f"--speed-weight must be >= 0 and finite, got {self.speed_weight}")
        if not 0.0 <= self.speed_free < 1.0:
            raise LolgpsError(f"--speed-free must be in [0, 1), got {self.speed_free}")


class CostExpansion(NamedTuple):
    """Per-sample quadratic expansion, sample-first: value ``[N, T]``, lx ``[N, T, dX]``,
    lu ``[N, T, dU]``, lxx ``[N, T, dX, dX]``, luu ``[N, T, dU, dU]``, lux ``[N, T, dU, dX]``."""

    value: Tensor
    lx: Tensor
    lu: Tensor
    lxx: Tensor
    luu: Tensor
    lux: Tensor


class PegCost:
    """Evaluates and expands the cost for batches of trajectories ``[N, T]``."""

    @classmethod
    def of(
        cls, config: CostConfig, arm: ArmSpec, kinematics: PegKinematics, layout: StateLayout
    ) -> PegCost:
        """The cost of ``arm``'s task, its torques and speeds in units of the arm's limits."""
        effort, velocity = (
            torch.tensor(v, dtype=torch.float64) for v in (arm.effort, arm.velocity)
        )
        return cls(config, kinematics, layout, effort, velocity)

    def __init__(
        self,
        config: CostConfig,
        kinematics: PegKinematics,
        layout: StateLayout,
        effort: Tensor,
        velocity: Tensor | None = None,
    ) -> None:
        """``effort``, ``velocity``: the joints' torque and velocity limits ``[dU]`` (no
        velocity limits: no speed cost)."""
        self.config = config
        self.kinematics = kinematics
        self.layout = layout
        dev = kinematics.device
        self.wu = config.action_weight / effort.to(dtype=torch.float64, device=dev) ** 2
        limit = (
            torch.full_like(self.wu, math.inf)
            if velocity is None
            else velocity.to(dtype=torch.float64, device=dev)
        )
        self.wv = config.speed_weight / limit**2  # 0 without limits
        self.free = config.speed_free * limit  # the speed below which motion is free
        axis = torch.tensor(
            [config.lateral_weight, config.lateral_weight, config.vertical_weight],
            dtype=torch.float64,
            device=dev,
        )
        A = torch.zeros(8, 6, dtype=torch.float64, device=dev)
        A[:6, :6] = torch.diag(axis.repeat(2).sqrt())
        tilt = config.tilt_weight**0.5
        A[6, 0], A[6, 3], A[7, 1], A[7, 4] = tilt, -tilt, tilt, -tilt
        self.A = A  # [8, 6]

    def _multiplier(self, T: int, like: Tensor) -> Tensor:
        m = torch.ones(T, dtype=like.dtype, device=like.device)
        m[-1] = self.config.final_multiplier
        return m

    def _targets(self, targets: Tensor, T: int) -> Tensor:
        """Per-step targets p*_t, broadcast against the points ``[N, T, 2, 3]``, from p*
        ``[2, 3]`` (one condition) or ``[N, 1, 2, 3]`` (one per sample)."""
        c = self.config
        if c.descent_height <= 0.0 or c.descent_steps <= 0:
            return targets
        t = torch.arange(T, dtype=targets.dtype, device=targets.device)
        lift = targets.new_zeros(T, 1, 3)
        lift[:, 0, 2] = c.descent_height * (1.0 - t / c.descent_steps).clamp(min=0.0)
        return targets + lift

    def _l12(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """Value and sqrt term ``s = sqrt(gamma + |z|^2)`` for ``z: [..., 8]``."""
        c = self.config
        sq = (z * z).sum(-1)
        s = torch.sqrt(c.gamma + sq)
        return 0.5 * c.l2 * sq + c.l1 * s, s

    def evaluate(self, x: Tensor, u: Tensor, targets: Tensor) -> Tensor:
        """Per-step cost ``[N, T]`` for x ``[N, T, dX]``, u ``[N, T, dU]``, targets ``[2, 3]``."""
        q = x[..., self.layout.q]
        targets_t = self._targets(targets, x.shape[-2])
        d = (self.kinematics.points(q) - targets_t).flatten(-2)  # [N, T, 6]
        value, _ = self._l12(d @ self.A.T)
        return self._effort(x, u) + self._multiplier(x.shape[-2], x) * value

    def _excess(self, x: Tensor) -> Tensor:
        """``e = max(0, |q-dot| - s v)`` per joint, ``[..., dU]``."""
        return (x[..., self.layout.qd].abs() - self.free).clamp(min=0.0)

    def _effort(self, x: Tensor, u: Tensor) -> Tensor:
        """The action and speed terms ``1/2 sum wu u^2 + 1/2 sum wv e^2``, ``[N, T]``."""
        e = self._excess(x)
        return 0.5 * (self.wu * u * u).sum(-1) + 0.5 * (self.wv * e * e).sum(-1)

    def expand(self, x: Tensor, u: Tensor, targets: Tensor) -> CostExpansion:
        """Value, gradient and Gauss-Newton Hessian at every sample and step."""
        c = self.config
        N, T, dX = x.shape
        dU = u.shape[-1]
        q = x[..., self.layout.q]
        d = (self.kinematics.points(q) - self._targets(targets, T)).flatten(-2)
        z = d @ self.A.T  # [N, T, 8]
        value, s = self._l12(z)
        g = (c.l2 + c.l1 / s)[..., None] * z  # dl12/dz
        eye = torch.eye(8, dtype=x.dtype, device=x.device)
        H = (c.l2 + c.l1 / s)[..., None, None] * eye - (c.l1 / s**3)[..., None, None] * (
            z[..., :, None] * z[..., None, :]
        )
        m = self._multiplier(T, x)
        AJ = self.A @ self.kinematics.jacobian(q)  # [N, T, 8, n]
        lq = m[:, None] * torch.einsum("ntzq,ntz->ntq", AJ, g)
        lqq = m[:, None, None] * AJ.transpose(-1, -2) @ H @ AJ

        qd = self.layout.qd
        lx = x.new_zeros(N, T, dX)
        lx[..., self.layout.q] = lq
        e = self._excess(x)
        lx[..., qd] = self.wv * e * x[..., qd].sign()
        lxx = x.new_zeros(N, T, dX, dX)
        lxx[..., self.layout.q, self.layout.q] = lqq
        lxx[..., qd, qd] = torch.diag_embed(self.wv * (e > 0))
        lu = self.wu * u
        luu = torch.diag_embed(self.wu.expand(N, T, dU))
        lux = x.new_zeros(N, T, dU, dX)
        total = self._effort(x, u) + m * value
        return CostExpansion(total, lx, lu, lxx, luu, lux)


def to_quadratic(expansion: CostExpansion, x: Tensor, u: Tensor) -> QuadraticCost:
    """Average the per-sample expansions into one quadratic in absolute coordinates.

    Around each sample y_n = [x_n; u_n]: l(y) ~ l_n + g_n^T (y - y_n) + 1/2 (y - y_n)^T H_n (y - y_n),
    so C = mean H_n, c = mean (g_n - H_n y_n), cc = mean (l_n - g_n^T y_n + 1/2 y_n^T H_n y_n).
    """
    e = expansion
    y = torch.cat([x, u], dim=-1)  # [N, T, dY]
    g = torch.cat([e.lx, e.lu], dim=-1)
    H = torch.cat(
        [torch.cat([e.lxx, e.lux.transpose(-1, -2)], -1), torch.cat([e.lux, e.luu], -1)], -2
    )
    Hy = (H @ y[..., None])[..., 0]
    C = H.mean(0)
    c = (g - Hy).mean(0)
    cc = (e.value - (g * y).sum(-1) + 0.5 * (y * Hy).sum(-1)).mean(0)
    return QuadraticCost(C, c, cc)
