"""Trajectory optimisation: the KL-constrained C-step (paper eq. 7), its step size, and the
C-step iterated on a model before any sample."""

from lolgps_torch.trajopt.config import CStepConfig
from lolgps_torch.trajopt.cstep import CStepResult, c_step
from lolgps_torch.trajopt.lqr import BackwardPassResult, backward_pass
from lolgps_torch.trajopt.plan import plan_on_model
from lolgps_torch.trajopt.step_size import adapt_step_mult, kl_bound, laplace_cost

__all__ = [
    "BackwardPassResult",
    "CStepConfig",
    "CStepResult",
    "adapt_step_mult",
    "backward_pass",
    "c_step",
    "kl_bound",
    "laplace_cost",
    "plan_on_model",
]
