"""One autograd graph: the distillation loss reaches alpha and the cost weights through p_act
and the C-step, and its gradient agrees with finite differences."""

from __future__ import annotations

import torch

from lolgps_torch.controllers import mix
from lolgps_torch.policy import kl_loss
from lolgps_torch.trajopt import c_step
from lolgps_torch.types import DistillBatch, LinearDynamics, LinearGaussian, QuadraticCost

T, dX, dU = 8, 4, 2


def _problem() -> tuple[LinearDynamics, QuadraticCost, QuadraticCost, LinearGaussian, torch.Tensor]:
    g = torch.Generator().manual_seed(0)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    F = torch.cat([torch.eye(dX) + 0.1 * randn(dX, dX), 0.3 * randn(dX, dU)], 1).expand(
        T - 1, -1, -1
    )
    dyn = LinearDynamics(
        F.clone(),
        0.05 * randn(T - 1, dX),
        0.01 * torch.eye(dX, dtype=torch.float64).expand(T - 1, dX, dX).clone(),
        randn(dX),
        0.1 * torch.eye(dX, dtype=torch.float64),
    )
    A = randn(T, dX + dU, dX + dU)
    state_cost = QuadraticCost(
        A @ A.transpose(-1, -2) / (dX + dU), randn(T, dX + dU), torch.zeros(T, dtype=torch.float64)
    )
    action = torch.zeros(T, dX + dU, dX + dU, dtype=torch.float64)
    action[:, dX:, dX:] = torch.eye(dU)
    action_cost = QuadraticCost(
        action, torch.zeros(T, dX + dU, dtype=torch.float64), torch.zeros(T, dtype=torch.float64)
    )
    p_pre = LinearGaussian(
        0.2 * randn(T, dU, dX),
        randn(T, dU),
        0.5 * torch.eye(dU, dtype=torch.float64).expand(T, dU, dU).clone(),
    )
    x = randn(T, dX)  # states where the targets are read
    return dyn, state_cost, action_cost, p_pre, x


def _loss(alpha: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """S-step loss of a fixed policy against p_act = alpha p_pre + (1 - alpha) p_cur(w), where
    p_cur is the C-step's answer for the cost state_cost + w * action_cost."""
    dyn, state_cost, action_cost, p_pre, x = _problem()
    cost = QuadraticCost(*(a + w * b for a, b in zip(state_cost, action_cost, strict=True)))
    p_cur = c_step(cost, dyn, p_pre, epsilon=1e6).policy  # epsilon large: eta stays at eta_min
    p_act = mix(p_pre, p_cur, alpha)
    batch = DistillBatch(
        x=x,
        mean_cur=p_act.mean_action(x[None])[0],
        prec_cur=p_act.precision(),
        mean_pre=p_pre.mean_action(x[None])[0],
        prec_pre=p_pre.precision(),
        has_pre=torch.ones(T, dtype=torch.bool),
    )
    policy_mean = torch.zeros(T, dU, dtype=torch.float64)
    return kl_loss(policy_mean, 0.3 * torch.eye(dU, dtype=torch.float64), batch)


def test_distillation_gradient_reaches_alpha_and_cost_weights() -> None:
    alpha = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    w = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    grad_alpha, grad_w = torch.autograd.grad(_loss(alpha, w), (alpha, w))
    assert grad_alpha.abs() > 1e-6 and grad_w.abs() > 1e-6
    h = 1e-5
    with torch.no_grad():
        fd_alpha = (_loss(alpha + h, w) - _loss(alpha - h, w)) / (2 * h)
        fd_w = (_loss(alpha, w + h) - _loss(alpha, w - h)) / (2 * h)
    assert torch.allclose(grad_alpha, fd_alpha, rtol=1e-5, atol=1e-7)
    assert torch.allclose(grad_w, fd_w, rtol=1e-5, atol=1e-7)
