"""The C-step iterated on a model of the dynamics before any sample (docs/ALGORITHM.md
section 4.2).

With the model prior and no samples, the dynamics posterior is the prior itself: the model
``x' = f(x, u)`` linearised along the predicted trajectory. From a controller p_0 whose mean
trajectory ``(xbar, ubar)`` under f is known, each round i = 0 .. R-1

1. linearises f at ``(xbar_t, ubar_t)``: ``x_{t+1} ~ F_t [x_t; u_t] + f_t``;
2. expands the cost at ``(xbar_t, ubar_t)`` into a quadratic;
3. takes the C-step ``p_{i+1} = argmin_p E_p[sum_t l] s.t. KL(p || p_i) <= epsilon`` under that
   linearisation (:func:`.cstep.c_step`) and gives p_{i+1} p_0's covariance;
4. moves ``(xbar, ubar)`` to p_{i+1}'s predicted state-action means.

Step 4 uses the linearisation's prediction, not a rollout of f: each round then costs one batched
linearisation and one C-step (a rollout of f is T sequential model steps, several times that),
and the trust region keeps the prediction near f's. The covariance stays p_0's so that the KL
bound moves only the mean, and the first samples explore around the planned mean as they would
around p_0.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from lolgps_torch.trajopt.config import CStepConfig
from lolgps_torch.trajopt.cstep import c_step
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost, StepLinearizer

# (x: [T, dX], u: [T, dU]) -> the cost's quadratic expansion at that trajectory
Expansion = Callable[[Tensor, Tensor], QuadraticCost]


def plan_on_model(
    linearize: StepLinearizer,
    expand: Expansion,
    start: LinearGaussian,
    x: Tensor,
    u: Tensor,
    rounds: int,
    epsilon: float,
    config: CStepConfig,
    state_var: float = 1e-6,
) -> LinearGaussian:
    """``rounds`` C-steps of size ``epsilon`` on the model from ``start``, whose mean trajectory
    under the model is ``x: [T, dX]``, ``u: [T, dU]``.

    :param state_var: variance of the linearised model's (deterministic) transitions and of
        the initial state ``x[0]``, which keeps the C-step's marginals positive definite.
    """
    dX = x.shape[-1]
    eye = torch.eye(dX, dtype=x.dtype, device=x.device)
    p = start
    for _ in range(rounds):
        F, f0 = linearize(x[:-1], u[:-1])
        noise = state_var * eye
        dynamics = LinearDynamics(F, f0, noise.expand(len(F), dX, dX), x[0], noise)
        result = c_step(expand(x, u), dynamics, p, epsilon, config)
        p = start._replace(K=result.policy.K, k=result.policy.k)
        x, u = result.mu[:, :dX], result.mu[:, dX:]
    return p
