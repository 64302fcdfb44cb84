"""Backward pass of the KL-constrained LQR (paper eq. 7, docs/ALGORITHM.md section 5).

For a dual variable eta the C-step solves a maximum-entropy LQR on the surrogate cost
``C / eta - log p_bar(u | x)``.  With ``P = cov_bar^{-1}`` and ``H = [-K_bar, -k_bar, I]`` the
second term is ``1/2 z^T H^T P H z`` in homogeneous coordinates ``z = [x; 1; u]``, i.e.
``Cyy += [[K_bar^T P K_bar, -K_bar^T P], [-P K_bar, P]]``, ``cy += [K_bar^T P k_bar; -P k_bar]``.

Here the whole surrogate is multiplied by eta, ``C + eta H^T P H``: K and k do not change, the
covariance is ``eta Quu^{-1}``, and both limits stay finite (eta -> 0 is plain LQR on C,
eta -> inf returns p_bar).  In homogeneous coordinates one matrix carries Qyy and qy:

    Q_t = C_t + eta D_t + Fa_t^T V_{t+1} Fa_t,     Fa_t = [[Fx, f, Fu], [0, 1, 0]]
    [K_t, k_t] = -Quu^{-1} Qu[x;1],                cov_t = eta Quu^{-1}
    V_t = Q[x;1][x;1] - Q[x;1]u Quu^{-1} Qu[x;1]   (symmetrised)

which is docs/ALGORITHM.md's ``Qyy = Cyy + F^T V F``, ``qy = cy + F^T (v + V f)``, ``V = Qxx + Qxu K``,
``v = qx + Qxu k`` written in one product.  Candidates eta ``[E]`` are solved as one batch.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.errors import NumericalError
from lolgps_torch.trajopt.config import CStepConfig
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost


class AugmentedProblem(NamedTuple):
    """The LQR data in ``z = [x; 1; u]`` (``dZ = dX + 1 + dU``), time-first.

    C: ``[T, dZ, dZ]`` cost, D: ``[T, dZ, dZ]`` quadratic form of ``-log p_bar``,
    F: ``[T-1, dX+1, dZ]`` dynamics of ``[x; 1]``.
    """

    C: Tensor
    D: Tensor
    F: Tensor

    @property
    def dX(self) -> int:
        return int(self.F.shape[-2]) - 1


class BackwardPassResult(NamedTuple):
    """Controllers with a leading candidate dimension ``E`` (K ``[E, T, dU, dX]``, k
    ``[E, T, dU]``, cov ``[E, T, dU, dU]``) and the eta ``[E]`` each was solved at (raised where
    Quu was not positive definite at the requested eta)."""

    policy: LinearGaussian
    eta: Tensor


def augment(
    cost: QuadraticCost, dynamics: LinearDynamics, p_bar: LinearGaussian
) -> AugmentedProblem:
    """Cost, ``-log p_bar`` and dynamics in homogeneous coordinates ``z = [x; 1; u]``."""
    T, dU, dX = p_bar.K.shape
    dY = dX + dU
    zero = cost.cc.new_zeros(T, 1, 1)
    Cy1 = torch.cat(
        [
            torch.cat([cost.C, cost.c.unsqueeze(-1)], -1),
            torch.cat([cost.c.unsqueeze(-2), zero], -1),
        ],
        dim=-2,
    )  # [T, dY+1, dY+1] in [x; u; 1]
    perm = [*range(dX), dY, *range(dX, dY)]
    C = Cy1[:, perm][:, :, perm]
    eye = torch.eye(dU, dtype=p_bar.K.dtype, device=p_bar.K.device).expand(T, dU, dU)
    # H z = u - K_bar x - k_bar, [T, dU, dZ]
    H = torch.cat([-p_bar.K, -p_bar.k.unsqueeze(-1), eye], dim=-1)
    P = torch.cholesky_inverse(torch.linalg.cholesky(p_bar.cov))
    D = H.mT @ P @ H
    Fx, Fu = dynamics.F[..., :dX], dynamics.F[..., dX:]
    top = torch.cat([Fx, dynamics.f.unsqueeze(-1), Fu], dim=-1)  # [T-1, dX, dZ]
    one = torch.zeros_like(top[:, :1, :])
    one[:, 0, dX] = 1.0
    return AugmentedProblem(C=C, D=D, F=torch.cat([top, one], dim=-2))


def solve(problem: AugmentedProblem, eta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """One batched backward pass at candidates ``eta [E]``, no retry.

    :return: gains ``[K, k]`` ``[E, T, dU, dX+1]``, Cholesky factors of Quu ``[E, T, dU, dU]``
        and ``ok [E]``, false where some Quu was not positive definite (that candidate's
        outputs are then meaningless).
    """
    dXa = problem.dX + 1
    E = eta.shape[0]
    w = eta[:, None, None]
    C, D = problem.C.unbind(0), problem.D.unbind(0)
    F = problem.F.unsqueeze(1).expand(-1, E, -1, -1)  # [T-1, E, dX+1, dZ]
    F_t, FT_t = F.unbind(0), F.mT.unbind(0)
    T = len(C)
    halves: list[Tensor] = []
    factors: list[Tensor] = []
    infos: list[Tensor] = []
    V: Tensor | None = None  # [E, dX+1, dX+1]
    for t in range(T - 1, -1, -1):
        Q = torch.addcmul(C[t], w, D[t])  # [E, dZ, dZ]
        if V is not None:
            Q = torch.baddbmm(Q, FT_t[t], torch.bmm(V, F_t[t]))  # + F^T V F
        L, info = torch.linalg.cholesky_ex(Q[:, dXa:, dXa:])  # Quu = L L^T
        R = torch.linalg.solve_triangular(L, Q[:, dXa:, :dXa], upper=False)  # L^{-1} Qu[x;1]
        V = torch.baddbmm(Q[:, :dXa, :dXa], R.mT, R, alpha=-1.0)  # Qxx - Qxu Quu^{-1} Qux
        V = torch.add(V, V.mT).mul_(0.5)
        halves.append(R)
        factors.append(L)
        infos.append(info)
    L_all = torch.stack(factors[::-1], dim=1)  # [E, T, dU, dU]
    gain = -torch.linalg.solve_triangular(L_all.mT, torch.stack(halves[::-1], dim=1), upper=True)
    ok = (torch.stack(infos) == 0).all(0) & torch.isfinite(gain.sum((1, 2, 3)))
    return gain, L_all, ok


def solve_with_retry(
    problem: AugmentedProblem,
    eta: Tensor,
    pd_delta: float = CStepConfig.pd_delta,
    eta_max: float = CStepConfig.eta_max,
    retry_width: int = CStepConfig.pd_retry_width,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`solve`, raising each failed candidate's eta to ``eta + pd_delta 2^j`` with the
    smallest j that makes every Quu positive definite; ``retry_width`` values of j are tried
    in one batch per round, up to ``eta_max``.

    :return: gains ``[E, T, dU, dX+1]``, Cholesky factors ``[E, T, dU, dU]``, the etas used
        ``[E]`` and ``solved [E]``: False where Quu is still not positive definite at
        ``eta_max`` (those rows' gains and factors are not usable; see :func:`require_solved`).
    """
    gain, factor, ok = solve(problem, eta)
    eta = eta.clone()
    solved = torch.ones_like(ok)
    failed = torch.nonzero(~ok).squeeze(-1)
    base = eta[failed]
    delta = torch.full_like(base, pd_delta)
    powers = 2.0 ** torch.arange(retry_width, dtype=eta.dtype, device=eta.device)
    while failed.numel() > 0:
        trial = (base[:, None] + delta[:, None] * powers).clamp(max=eta_max)  # [n, width]
        trial_gain, trial_factor, trial_ok = solve(problem, trial.flatten())
        trial_ok = trial_ok.view(trial.shape)
        found = trial_ok.any(1)
        first = torch.argmax(trial_ok.to(torch.int8), dim=1)  # first PD trial of each row
        pick = (torch.arange(len(failed), device=eta.device) * retry_width + first)[found]
        gain = gain.index_copy(0, failed[found], trial_gain[pick])
        factor = factor.index_copy(0, failed[found], trial_factor[pick])
        eta = eta.index_copy(0, failed[found], trial.flatten()[pick])
        given_up = ~found & (trial[:, -1] >= eta_max)
        solved[failed[given_up]] = False
        keep = ~found & ~given_up
        failed, base, delta = failed[keep], base[keep], delta[keep] * 2.0**retry_width
    return gain, factor, eta, solved


def require_solved(solved: Tensor, eta_max: float) -> None:
    """Raise :class:`NumericalError` unless every candidate of ``solved [E]`` was solved."""
    if not bool(solved.all()):
        raise NumericalError(
            f"Quu is not positive definite even at eta = {eta_max:g}: the cost is not "
            "convex enough in u for this p_bar (check the action weights and p_bar.cov)"
        )


def to_policy(gain: Tensor, factor: Tensor, eta: Tensor) -> LinearGaussian:
    """Controllers ``[E, T, ...]`` from gains ``[K, k]``, Quu factors and eta:
    ``cov = eta Quu^{-1}``."""
    cov = eta[:, None, None, None] * torch.cholesky_inverse(factor)
    return LinearGaussian(K=gain[..., :-1], k=gain[..., -1], cov=cov)


def backward_pass(
    cost: QuadraticCost,
    dynamics: LinearDynamics,
    p_bar: LinearGaussian,
    eta: Tensor,
    pd_delta: float = CStepConfig.pd_delta,
    eta_max: float = CStepConfig.eta_max,
    retry_width: int = CStepConfig.pd_retry_width,
) -> BackwardPassResult:
    """LQR on ``C / eta - log p_bar`` for each candidate of ``eta [E]`` in one batched pass.

    Differentiable by autograd in ``cost``, ``dynamics`` and ``p_bar`` (eta is held fixed).
    Where a candidate's Quu is not positive definite its eta is raised by ``pd_delta``, doubling,
    until it is (:func:`solve_with_retry`).

    :param eta: dual-variable candidates ``[E]`` (detached).
    :raises LolgpsError: when Quu is not positive definite even at ``eta_max``.
    """
    problem = augment(cost, dynamics, p_bar)
    gain, factor, eta, solved = solve_with_retry(
        problem, eta.detach(), pd_delta, eta_max, retry_width
    )
    require_solved(solved, eta_max)
    return BackwardPassResult(policy=to_policy(gain, factor, eta), eta=eta)
