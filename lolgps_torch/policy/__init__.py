"""The global policy (docs/ALGORITHM.md sections 6-7): the net, its linearisation ``p_pre`` and the
S-step."""

from lolgps_torch.policy.actor import policy_actor
from lolgps_torch.policy.linearize import jacobian_controller, linearize_policy
from lolgps_torch.policy.net import GaussianPolicy, PolicyConfig
from lolgps_torch.policy.sstep import distill, kl_loss, optimal_variance

__all__ = [
    "GaussianPolicy",
    "PolicyConfig",
    "distill",
    "jacobian_controller",
    "kl_loss",
    "linearize_policy",
    "optimal_variance",
    "policy_actor",
]
