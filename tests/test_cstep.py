"""C-step (paper eq. 7): against a Riccati recursion written here, the KL constraint, gradients
against finite differences, and the positive-definiteness retry."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from lolgps_torch.controllers import forward_pass, kl_divergence
from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.trajopt import (
    CStepConfig,
    adapt_step_mult,
    backward_pass,
    c_step,
    kl_bound,
    laplace_cost,
    lqr,
)
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost

DT = torch.float64


def _spd(n: int, *batch: int, g: torch.Generator, scale: float = 1.0) -> Tensor:
    M = torch.randn(*batch, n, n, generator=g, dtype=DT)
    return scale * (M @ M.mT / n + 0.1 * torch.eye(n, dtype=DT))


def random_problem(
    T: int = 20, dX: int = 6, dU: int = 3, seed: int = 0
) -> tuple[QuadraticCost, LinearDynamics, LinearGaussian]:
    """A random time-varying linear system, a random convex quadratic cost and a random p_bar."""
    g = torch.Generator().manual_seed(seed)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=g, dtype=DT)

    A = torch.eye(dX, dtype=DT) + 0.1 * randn(T - 1, dX, dX)
    dynamics = LinearDynamics(
        F=torch.cat([A, 0.3 * randn(T - 1, dX, dU)], dim=-1),
        f=0.1 * randn(T - 1, dX),
        cov=_spd(dX, T - 1, g=g, scale=0.01),
        x0_mean=randn(dX),
        x0_cov=_spd(dX, g=g, scale=0.1),
    )
    cost = QuadraticCost(C=_spd(dX + dU, T, g=g), c=randn(T, dX + dU), cc=randn(T))
    p_bar = LinearGaussian(K=0.1 * randn(T, dU, dX), k=randn(T, dU), cov=_spd(dU, T, g=g))
    return cost, dynamics, p_bar


def riccati(cost: QuadraticCost, dynamics: LinearDynamics) -> tuple[Tensor, Tensor]:
    """Plain finite-horizon LQR with affine dynamics x' = F [x; u] + f (independent of the
    library): Q = C + F^T V F, q = c + F^T (v + V f), K = -Quu^-1 Qux, k = -Quu^-1 qu."""
    T, dY = cost.c.shape
    dX = dynamics.x0_mean.shape[0]
    V = torch.zeros(dX, dX, dtype=DT)
    v = torch.zeros(dX, dtype=DT)
    Ks, ks = [], []
    for t in reversed(range(T)):
        Q, q = cost.C[t].clone(), cost.c[t].clone()
        if t < T - 1:
            F, f = dynamics.F[t], dynamics.f[t]
            Q = Q + F.T @ V @ F
            q = q + F.T @ (v + V @ f)
        Qxx, Qxu, Qux, Quu = Q[:dX, :dX], Q[:dX, dX:], Q[dX:, :dX], Q[dX:, dX:]
        K = -torch.linalg.solve(Quu, Qux)
        k = -torch.linalg.solve(Quu, q[dX:])
        V = Qxx + Qxu @ K
        V = 0.5 * (V + V.T)
        v = q[:dX] + Qxu @ k
        Ks.append(K)
        ks.append(k)
    return torch.stack(Ks[::-1]), torch.stack(ks[::-1])


def test_unconstrained_matches_riccati() -> None:
    cost, dynamics, p_bar = random_problem()
    result = c_step(cost, dynamics, p_bar, epsilon=1e6)
    # The constraint does not bind, so the C-step stops at eta_min = 1e-8: the LQR on
    # C + eta_min * (-log p_bar), whose gains differ from plain LQR by O(eta_min |P_bar| / |C|).
    assert float(result.eta) == pytest.approx(CStepConfig().eta_min)
    assert result.num_passes == 1 and result.converged
    K, k = riccati(cost, dynamics)
    torch.testing.assert_close(result.policy.K, K, rtol=0.0, atol=1e-6)
    torch.testing.assert_close(result.policy.k, k, rtol=0.0, atol=1e-6)
    # The covariance is eta Quu^{-1}: positive definite and tiny.
    assert bool((torch.linalg.eigvalsh(result.policy.cov) > 0).all())
    assert float(result.policy.cov.abs().max()) < 1e-6


@pytest.mark.parametrize("epsilon", [5.0, 20.0, 60.0])
def test_binding_constraint_meets_epsilon(epsilon: float) -> None:
    cost, dynamics, p_bar = random_problem(seed=1)
    config = CStepConfig()
    loose = c_step(cost, dynamics, p_bar, epsilon=1e6, config=config)
    assert float(loose.kl.sum()) > 2 * epsilon  # the constraint binds
    result = c_step(cost, dynamics, p_bar, epsilon=epsilon, config=config)
    assert result.converged
    kl = kl_divergence(result.policy, p_bar, *forward_pass(result.policy, dynamics)).sum()
    assert abs(float(kl) - epsilon) <= config.kl_tolerance * epsilon
    torch.testing.assert_close(result.kl.sum(), kl)
    torch.testing.assert_close((result.mu, result.sigma), forward_pass(result.policy, dynamics))
    # Trading cost for KL: the constrained controller costs more than the unconstrained one.
    assert float(laplace_cost(result.policy, dynamics, cost)) > float(
        laplace_cost(loose.policy, dynamics, cost)
    )


def test_unfinished_search_stays_inside_the_constraint() -> None:
    cost, dynamics, p_bar = random_problem(seed=1)
    with pytest.warns(UserWarning, match="did not reach"):
        result = c_step(cost, dynamics, p_bar, epsilon=20.0, config=CStepConfig(max_passes=1))
    assert not result.converged and result.num_passes == 1
    assert float(result.kl.sum()) < 20.0


def test_large_eta_returns_p_bar() -> None:
    cost, dynamics, p_bar = random_problem(seed=2)
    solved = backward_pass(cost, dynamics, p_bar, torch.tensor([1e12], dtype=DT)).policy
    for got, want in zip(solved, p_bar, strict=True):
        torch.testing.assert_close(got[0], want, rtol=1e-6, atol=1e-9)


def test_batched_candidates_match_single_solves() -> None:
    cost, dynamics, p_bar = random_problem(seed=3)
    eta = torch.tensor([0.1, 1.0, 10.0], dtype=DT)
    batched = backward_pass(cost, dynamics, p_bar, eta).policy
    for i in range(3):
        single = backward_pass(cost, dynamics, p_bar, eta[i : i + 1]).policy
        for got, want in zip(batched, single, strict=True):
            torch.testing.assert_close(got[i], want[0])


def _scaled_cost(cost: QuadraticCost, weight: Tensor) -> QuadraticCost:
    """The cost with its action block scaled by ``weight`` (a cost weight to differentiate)."""
    dU = 3
    mask = torch.zeros_like(cost.C)
    mask[:, -dU:, -dU:] = 1.0
    return QuadraticCost(C=cost.C + (weight - 1.0) * mask * cost.C, c=cost.c, cc=cost.cc)


def _output(policy: LinearGaussian, mu: Tensor, kl: Tensor) -> Tensor:
    """A scalar of a controller, its marginal means and its KL."""
    return policy.k.sum() + policy.K.sum() + policy.cov.sum() + mu.sum() + kl.sum()


def _solve_at(
    cost: QuadraticCost, dynamics: LinearDynamics, p_bar: LinearGaussian, eta: Tensor
) -> Tensor:
    """``_output`` of the controller solved at a fixed eta."""
    batched = backward_pass(cost, dynamics, p_bar, eta[None]).policy
    policy = LinearGaussian(*(part[0] for part in batched))
    mu, sigma = forward_pass(policy, dynamics)
    return _output(policy, mu, kl_divergence(policy, p_bar, mu, sigma))


@pytest.mark.parametrize("epsilon", [20.0, 1e6])
def test_gradient_matches_finite_differences(epsilon: float) -> None:
    cost, dynamics, p_bar = random_problem(seed=4)
    weight = torch.tensor(1.3, dtype=DT, requires_grad=True)
    result = c_step(_scaled_cost(cost, weight), dynamics, p_bar, epsilon=epsilon)
    (grad,) = torch.autograd.grad(_output(result.policy, result.mu, result.kl), weight)
    # The returned controller, marginals and KL are differentiable at the chosen eta, held fixed.
    h = 1e-6
    with torch.no_grad():
        plus, minus = (
            _solve_at(_scaled_cost(cost, weight + s), dynamics, p_bar, result.eta) for s in (h, -h)
        )
    torch.testing.assert_close(grad, (plus - minus) / (2 * h), rtol=1e-5, atol=1e-8)


def test_backward_pass_gradcheck() -> None:
    cost, dynamics, p_bar = random_problem(T=3, dX=2, dU=2, seed=5)
    eta = torch.tensor([0.5, 3.0], dtype=DT)

    def solve(C: Tensor, F: Tensor, K_bar: Tensor, k_bar: Tensor, cov_bar: Tensor) -> Tensor:
        cov_bar = 0.5 * (cov_bar + cov_bar.mT)
        policy = backward_pass(
            QuadraticCost(0.5 * (C + C.mT), cost.c, cost.cc),
            dynamics._replace(F=F),
            LinearGaussian(K_bar, k_bar, cov_bar),
            eta,
        ).policy
        return torch.cat([part.flatten() for part in policy])

    inputs = tuple(t.clone().requires_grad_() for t in (cost.C, dynamics.F, *p_bar))
    assert torch.autograd.gradcheck(solve, inputs)


def test_indefinite_quu_raises_eta() -> None:
    cost, dynamics, p_bar = random_problem(seed=6)
    # Concave in u at the last step: Quu = Cuu + eta P_bar needs eta above a threshold.
    C = cost.C.clone()
    C[-1, -3:, -3:] = -2.0 * torch.eye(3, dtype=DT)
    cost = cost._replace(C=C)
    solved = backward_pass(cost, dynamics, p_bar, torch.tensor([1e-8, 1e3], dtype=DT))
    assert float(solved.eta[0]) > 1e-4  # raised by the retry
    assert float(solved.eta[1]) == 1e3  # already positive definite: untouched
    assert bool((torch.linalg.eigvalsh(solved.policy.cov) > 0).all())
    result = c_step(cost, dynamics, p_bar, epsilon=1e6)
    assert float(result.eta) > 1e-4
    assert bool(torch.isfinite(result.policy.K).all())
    assert bool((torch.linalg.eigvalsh(result.policy.cov) > 0).all())


def test_impossible_quu_raises() -> None:
    cost, dynamics, p_bar = random_problem(seed=7)
    C = cost.C.clone()
    C[-1, -3:, -3:] = -1e20 * torch.eye(3, dtype=DT)
    cost = cost._replace(C=C)
    with pytest.raises(LolgpsError, match="not positive definite"):
        backward_pass(cost, dynamics, p_bar, torch.tensor([1.0], dtype=DT))
    with pytest.raises(LolgpsError, match="not positive definite"):
        c_step(cost, dynamics, p_bar, epsilon=10.0)


def test_candidates_that_rounding_breaks_leave_the_search(monkeypatch: pytest.MonkeyPatch) -> None:
    """When Quu fails at the largest etas alone (rounding, as on fitted contact dynamics),
    those candidates leave the dual search instead of ending it: a bound the solvable etas
    reach is met as without the failure, and a bound below their KL keeps the solvable
    controller closest to p_bar, with a warning."""
    cost, dynamics, p_bar = random_problem(seed=8)
    reference = c_step(cost, dynamics, p_bar, epsilon=5.0)
    real = lqr.solve

    def broken_above(limit: float):  # type: ignore[no-untyped-def]
        def solve(problem: lqr.AugmentedProblem, eta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            gain, factor, ok = real(problem, eta)
            return gain, factor, ok & (eta < limit)

        return solve

    monkeypatch.setattr(lqr, "solve", broken_above(1e6))
    result = c_step(cost, dynamics, p_bar, epsilon=5.0)
    assert float(result.eta) < 1e6
    torch.testing.assert_close(result.policy.K, reference.policy.K, rtol=1e-3, atol=1e-6)
    with pytest.warns(UserWarning, match="even at the largest eta"):
        tight = c_step(cost, dynamics, p_bar, epsilon=1e-9)
    assert float(tight.eta) < 1e6 and float(tight.kl.sum()) > 1e-9
    monkeypatch.setattr(lqr, "solve", broken_above(0.0))
    with pytest.raises(NumericalError, match="not positive definite"):
        c_step(cost, dynamics, p_bar, epsilon=5.0)


def test_a_fit_that_does_not_lead_back_to_p_bar_keeps_p_bar() -> None:
    """On dynamics that double the state every step for 100 steps the LQR at the largest eta
    is still far from p_bar (KL in the hundreds where it tends to 0): no eta can be trusted,
    and the C-step returns p_bar itself, KL 0, with a warning. On the same problem's stable
    dynamics it meets the bound as usual."""
    cost, dynamics, p_bar = random_problem(T=100, seed=1)
    stable = c_step(cost, dynamics, p_bar, epsilon=10.0)
    assert float(stable.kl.sum()) == pytest.approx(10.0, rel=0.1)
    F = dynamics.F.clone()
    F[..., : dynamics.x0_mean.shape[0]] *= 2.0
    with pytest.warns(UserWarning, match="do not lead the C-step back to p_bar"):
        kept = c_step(cost, dynamics._replace(F=F), p_bar, epsilon=10.0)
    for part, bar in zip(kept.policy, p_bar, strict=True):
        assert torch.equal(part, bar)
    assert float(kept.kl.abs().sum()) < 1e-6


def test_step_mult_adaptation() -> None:
    config = CStepConfig()
    assert kl_bound(2.0, 100, config) == pytest.approx(200.0)
    # Predicted improvement 10, actual 10: change = 10 / (2 * 1e-4) -> clipped to 5, then to 3.
    assert adapt_step_mult(1.0, 20.0, 10.0, 10.0, config) == pytest.approx(3.0)
    # Predicted 10, actual 6: change = 10 / 8 = 1.25.
    assert adapt_step_mult(1.0, 20.0, 10.0, 14.0, config) == pytest.approx(1.25)
    # Actual worse than before: change = 10 / (2 * 30) = 1/6.
    assert adapt_step_mult(1.0, 20.0, 10.0, 40.0, config) == pytest.approx(1.0 / 6.0)
    # Far worse: the change is clipped at 0.1, the multiplier at step_mult_min.
    assert adapt_step_mult(0.05, 20.0, 10.0, 1e4, config) == pytest.approx(0.01)


def test_config_rejects_bad_values() -> None:
    with pytest.raises(LolgpsError):
        CStepConfig(eta_min=0.0)
    with pytest.raises(LolgpsError):
        CStepConfig(step_mult_init=10.0)
