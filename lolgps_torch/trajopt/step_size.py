"""KL step size and its adaptation (docs/ALGORITHM.md section 5, as the original MDGPS).

    epsilon   = kl_step * step_mult * T
    pred      = E[cost | p_prev, old model] - E[cost | p_new, old model]   (predicted improvement)
    actual    = E[cost | p_prev, old model] - E[cost | p_new, new model]   (actual improvement)
    change    = clip(pred / (2 max(1e-4, pred - actual)), 0.1, 5)
    step_mult = clip(step_mult * change, step_mult_min, step_mult_max)

The expected costs are the Laplace estimates of :func:`laplace_cost`.
"""

from __future__ import annotations

from torch import Tensor

from lolgps_torch.controllers import expected_cost, forward_pass
from lolgps_torch.trajopt.config import CStepConfig
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost


def kl_bound(step_mult: float, T: int, config: CStepConfig) -> float:
    """The trajectory KL bound ``epsilon = kl_step * step_mult * T``."""
    return config.kl_step * step_mult * T


def laplace_cost(policy: LinearGaussian, dynamics: LinearDynamics, cost: QuadraticCost) -> Tensor:
    """Expected total cost ``[]`` of ``policy`` under a dynamics model and a cost expansion:
    ``sum_t 1/2 tr(C_t S_t) + 1/2 mu_t^T C_t mu_t + mu_t^T c_t + cc_t``."""
    return expected_cost(cost, *forward_pass(policy, dynamics)).sum(-1)


def adapt_step_mult(
    step_mult: float,
    previous_cost: float | Tensor,
    predicted_cost: float | Tensor,
    actual_cost: float | Tensor,
    config: CStepConfig,
) -> float:
    """The next step multiplier from three expected total costs.

    :param step_mult: the current multiplier.
    :param previous_cost: the previous controller under the previous model and cost.
    :param predicted_cost: the new controller under the previous model and cost.
    :param actual_cost: the new controller under the model and cost fitted to its own samples.
    """
    predicted = float(previous_cost) - float(predicted_cost)
    actual = float(previous_cost) - float(actual_cost)
    change = predicted / (2.0 * max(1e-4, predicted - actual))
    change = min(max(change, config.step_change_min), config.step_change_max)
    return min(max(step_mult * change, config.step_mult_min), config.step_mult_max)
