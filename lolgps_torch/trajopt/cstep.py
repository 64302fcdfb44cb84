"""The C-step: KL-constrained trajectory optimisation (paper eq. 7, docs/ALGORITHM.md section 5).

    p_cur = argmin_p E_p[sum_t l(x_t, u_t)]   s.t.   KL(p || p_bar) <= epsilon

For a dual variable eta the solution is the LQR on ``C / eta - log p_bar`` (:mod:`.lqr`), and
its KL decreases with eta.  The dual search evaluates ``num_candidates`` values of eta as one
batched backward pass plus one batched KL pass: first a log-spaced grid over
``[eta_min, eta_max]``, then a grid inside the bracket where KL crosses epsilon, centred on a
monotone cubic interpolate of log KL against log eta, until ``|KL - epsilon| <= tol epsilon``
(usually two passes).  When even ``eta_min`` gives ``KL <= (1 + tol) epsilon`` the constraint
does not bind and that solution, LQR on ``C + eta_min (-log p_bar)``, is returned.

As eta grows the solution tends to p_bar and its KL to 0: at ``eta_max`` it is below
``tol epsilon`` on every fit that describes its samples (at most 0.06 against epsilon >= 1 over
a whole KUKA stream learnt by the sample-only GMM prior).  A fit under which it is not (the
Panda's first samples of a controller planned on its model, five rollouts fitted by the GMM
prior alone: KL 50 at ``eta_max``, the controller's gains 500 from p_bar's, its predicted state
covariance 1e25) cannot place p between p_bar and the cost's optimum, and p_bar itself, KL 0,
is returned with a warning: the learner samples p_bar again rather than step on that fit.

The search runs without autograd.  When an input requires a gradient the controller is
solved once more at the chosen eta, held fixed, so that it is differentiable in the cost, the
dynamics and p_bar (the dependence of eta itself on them is not included); otherwise the
search's own candidate is returned.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import torch
from torch import Tensor

from lolgps_torch.controllers import (
    joint_marginals,
    kl_divergence,
    state_marginals,
    trajectory_kl,
)
from lolgps_torch.trajopt.config import CStepConfig
from lolgps_torch.trajopt.lqr import (
    AugmentedProblem,
    augment,
    require_solved,
    solve_with_retry,
    to_policy,
)
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost


class CStepResult(NamedTuple):
    """Outcome of a C-step.

    policy: the new controller (K ``[T, dU, dX]``, k ``[T, dU]``, cov ``[T, dU, dU]``);
    eta: ``[]`` the dual variable it was solved at (detached);
    kl: ``[T]`` per-step KL to p_bar under its own marginals (the sum is the trajectory KL);
    mu: ``[T, dY]``, sigma: ``[T, dY, dY]`` its state-action marginals under the dynamics;
    num_passes: batched passes of the dual search; converged: ``|KL - epsilon| <= tol epsilon``
    was reached, or the constraint did not bind.
    """

    policy: LinearGaussian
    eta: Tensor
    kl: Tensor
    mu: Tensor
    sigma: Tensor
    num_passes: int
    converged: bool


class _Candidates(NamedTuple):
    """Evaluated candidates: ``eta [M]``, per-step ``kl [M, T]``, controllers ``[M, T, ...]``."""

    eta: Tensor
    kl: Tensor
    policy: LinearGaussian


def _evaluate(
    problem: AugmentedProblem,
    dynamics: LinearDynamics,
    p_bar: LinearGaussian,
    eta: Tensor,
    config: CStepConfig,
) -> _Candidates:
    gain, factor, eta, solved = solve_with_retry(
        problem, eta, config.pd_delta, config.eta_max, config.pd_retry_width
    )
    if not bool(solved.any()):  # no candidate solved: a numerical failure
        require_solved(solved, config.eta_max)
    keep = torch.nonzero(solved).squeeze(-1)  # rounding can break the largest etas alone
    policy = to_policy(gain[keep], factor[keep], eta[keep])
    return _Candidates(eta[keep], trajectory_kl(policy, p_bar, dynamics), policy)


class _Choice(NamedTuple):
    """Search state: ``done`` with ``candidate`` chosen (None: p_bar itself), or else the next
    ``grid`` of eta inside the bracket around epsilon, with ``candidate`` the one at its upper
    end (inside the constraint)."""

    done: bool
    candidate: int | None
    grid: Tensor


def _choose(eta: Tensor, kl: Tensor, epsilon: float, config: CStepConfig, window: bool) -> _Choice:
    """Pick from all candidates so far (``eta [M]``, trajectory ``kl [M]``), or place the next
    ``num_candidates`` inside the bracket ``(eta_lo, eta_hi)`` where KL crosses epsilon.

    KL(eta) is smooth and decreasing on a log-log scale.  With ``window`` the next grid is
    centred on the crossing of epsilon by a monotone cubic (PCHIP) interpolant of the log-log
    data, spaced so that neighbouring candidates' KL differ by at most ``(1 + tol) / (1 - tol)``
    at the interpolant's slope there (then one of them is within tolerance).  It covers the
    bracket evenly when that is narrow enough, or without ``window`` (after a window that
    missed, which guarantees the bracket shrinks).
    """
    tol = config.kl_tolerance
    order = torch.argsort(eta)
    distinct = torch.cat([order[:1], order[1:][eta[order].diff() > 0]])  # PD raises may collide
    order, kl_sorted = distinct, kl[distinct]
    if float(eta.max()) >= config.eta_max and kl_sorted[-1] > tol * epsilon:
        warnings.warn(
            f"KL to p_bar is {float(kl_sorted[-1]):.3g} at the largest eta {config.eta_max:.3g}, "
            f"not near 0 (epsilon = {epsilon:.3g}): the fitted dynamics do not lead the C-step "
            "back to p_bar; keeping p_bar",
            stacklevel=3,
        )
        return _Choice(True, None, eta[:0])
    if kl_sorted[0] <= (1.0 + tol) * epsilon:
        return _Choice(True, int(order[0]), eta[:0])
    error = (kl - epsilon).abs()
    best = int(torch.argmin(error))
    if error[best] <= tol * epsilon:
        return _Choice(True, best, eta[:0])
    below = torch.nonzero(kl_sorted < epsilon).squeeze(-1)
    if below.numel() == 0:  # the fitted dynamics amplify even p ~ p_bar: stay at p_bar
        warnings.warn(
            f"KL to p_bar is {float(kl_sorted[-1]):.3g} > epsilon = {epsilon:.3g} even at the "
            f"largest eta {float(eta.max()):.3g}; keeping that controller (closest to p_bar)",
            stacklevel=3,
        )
        return _Choice(True, int(order[-1]), eta[:0])
    hi = int(below[0])
    x = eta[order].log().tolist()
    y = kl_sorted.clamp_min(torch.finfo(kl.dtype).tiny).log().tolist()
    crossing, slope = _pchip_crossing(x, y, hi, math.log(epsilon))
    step = math.log((1.0 + tol) / (1.0 - tol)) / max(abs(slope), 1e-3)
    num = config.num_candidates
    if not window or x[hi] - x[hi - 1] <= step * (num + 1):
        grid = torch.linspace(x[hi - 1], x[hi], num + 2, dtype=eta.dtype, device=eta.device)
        grid = grid[1:-1]
    else:
        half = 0.5 * step * (num - 1)
        centre = min(max(crossing, x[hi - 1] + step + half), x[hi] - step - half)
        offsets = torch.arange(num, dtype=eta.dtype, device=eta.device) - 0.5 * (num - 1)
        grid = centre + step * offsets
    return _Choice(False, int(order[hi]), grid.exp())


def _pchip_crossing(x: list[float], y: list[float], hi: int, target: float) -> tuple[float, float]:
    """Where the monotone cubic Hermite interpolant of ``(x, y)`` (Fritsch-Carlson slopes)
    crosses ``target`` inside ``[x[hi-1], x[hi]]``, and its slope there; ``y`` decreasing."""
    secant = [(y[i + 1] - y[i]) / (x[i + 1] - x[i]) for i in range(len(x) - 1)]

    def node_slope(i: int) -> float:
        if i == 0 or i == len(x) - 1:
            return secant[min(i, len(secant) - 1)]
        a, b = secant[i - 1], secant[i]
        return 0.0 if a * b <= 0.0 else 2.0 / (1.0 / a + 1.0 / b)

    x0, width, y0, y1 = x[hi - 1], x[hi] - x[hi - 1], y[hi - 1], y[hi]
    m0, m1 = node_slope(hi - 1) * width, node_slope(hi) * width

    def value(s: float) -> float:
        return (
            (2 * s**3 - 3 * s**2 + 1) * y0
            + (s**3 - 2 * s**2 + s) * m0
            + (3 * s**2 - 2 * s**3) * y1
            + (s**3 - s**2) * m1
        )

    lo, up = 0.0, 1.0
    for _ in range(50):  # monotone on the interval: bisection
        mid = 0.5 * (lo + up)
        lo, up = (mid, up) if value(mid) > target else (lo, mid)
    s = 0.5 * (lo + up)
    derivative = (
        (6 * s**2 - 6 * s) * y0
        + (3 * s**2 - 4 * s + 1) * m0
        + (6 * s - 6 * s**2) * y1
        + (3 * s**2 - 2 * s) * m1
    )
    return x0 + s * width, derivative / width


def _dual_search(
    problem: AugmentedProblem,
    dynamics: LinearDynamics,
    p_bar: LinearGaussian,
    epsilon: float,
    config: CStepConfig,
) -> tuple[_Candidates, int | None, int, bool]:
    """Batched dual search: all candidates evaluated, the chosen one's index (None: p_bar),
    the number of passes and whether the tolerance was met."""
    like = problem.C
    grid = torch.logspace(
        math.log10(config.eta_min),
        math.log10(config.eta_max),
        config.num_candidates,
        dtype=like.dtype,
        device=like.device,
    )
    passes: list[_Candidates] = []
    for num_passes in range(1, config.max_passes + 1):
        passes.append(_evaluate(problem, dynamics, p_bar, grid, config))
        eta = torch.cat([c.eta for c in passes])
        kl = torch.cat([c.kl.sum(-1) for c in passes])
        window = num_passes % 2 == 1  # windows and even grids alternate
        choice = _choose(eta, kl, epsilon, config, window)
        if choice.done:
            return _concat(passes), choice.candidate, num_passes, True
        grid = choice.grid
    warnings.warn(
        f"C-step dual search did not reach |KL - epsilon| <= {config.kl_tolerance} epsilon in "
        f"{config.max_passes} passes; using the closest eta inside the constraint",
        stacklevel=3,
    )
    return _concat(passes), choice.candidate, config.max_passes, False


def _concat(passes: list[_Candidates]) -> _Candidates:
    if len(passes) == 1:
        return passes[0]
    return _Candidates(
        eta=torch.cat([c.eta for c in passes]),
        kl=torch.cat([c.kl for c in passes]),
        policy=LinearGaussian(
            K=torch.cat([c.policy.K for c in passes]),
            k=torch.cat([c.policy.k for c in passes]),
            cov=torch.cat([c.policy.cov for c in passes]),
        ),
    )


def c_step(
    cost: QuadraticCost,
    dynamics: LinearDynamics,
    p_bar: LinearGaussian,
    epsilon: float,
    config: CStepConfig | None = None,
) -> CStepResult:
    """New local controller minimising the expected cost with ``KL(p || p_bar) <= epsilon``.

    Differentiable by autograd in ``cost``, ``dynamics`` and ``p_bar`` at the chosen eta.

    :param cost: quadratic cost expansion ``[T, ...]``. :param dynamics: fitted dynamics.
    :param p_bar: the trust-region controller (p_pre, or the previous p_cur).
    :param epsilon: the KL bound on the whole trajectory (``kl_step * step_mult * T``).
    :param config: search settings; defaults to ``CStepConfig()``.
    :raises NumericalError: when Quu stays indefinite up to ``eta_max`` for every candidate.
    """
    config = CStepConfig() if config is None else config
    tensors = (*cost, *dynamics, *p_bar)
    with torch.no_grad():
        found, index, num_passes, converged = _dual_search(
            augment(cost, dynamics, p_bar), dynamics, p_bar, float(epsilon), config
        )
    if index is None:  # p_bar itself, at eta = infinity
        policy, eta = p_bar, p_bar.k.new_tensor(config.eta_max)
    elif torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        eta = found.eta[index]
        gain, factor, eta_used, solved = solve_with_retry(
            augment(cost, dynamics, p_bar),
            eta[None],
            config.pd_delta,
            config.eta_max,
            config.pd_retry_width,
        )
        require_solved(solved, config.eta_max)
        policy = LinearGaussian(*(part[0] for part in to_policy(gain, factor, eta_used)))
        eta = eta_used[0]
    else:
        policy = LinearGaussian(*(part[index] for part in found.policy))
        eta = found.eta[index]
    mu_x, sigma_x = state_marginals(policy, dynamics)
    kl = kl_divergence(policy, p_bar, mu_x, sigma_x)
    mu, sigma = joint_marginals(policy, mu_x, sigma_x)
    return CStepResult(policy, eta.detach(), kl, mu, sigma, num_passes, converged)
