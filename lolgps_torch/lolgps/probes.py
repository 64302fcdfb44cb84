"""The probes: noiseless rollouts that check a controller or the global policy at a condition
(counted as the arm's ``probe`` rollouts), the stream's checks before, during and after it."""

from __future__ import annotations

import math

import torch

from lolgps_torch.errors import NumericalError
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.policy.actor import controller_actor
from lolgps_torch.task import PegTask
from lolgps_torch.types import LinearGaussian


def noiseless_distance(
    task: PegTask,
    p: LinearGaussian,
    offset: tuple[float, float],
    limits: tuple[float, float] | None,
) -> float:
    """Final distance (m) of the controller ``p``'s noiseless rollout at ``offset``, kept
    within ``limits`` as its samples are (:func:`~lolgps_torch.policy.actor.controller_actor`)."""
    zero = torch.zeros(1, task.T, task.layout.dU, dtype=torch.float64, device=task.device)
    actor = controller_actor(p, zero, task.model, limits)
    return float(task.sample(actor, [offset], "probe").scored_distance[0])


def policy_distances(
    task: PegTask, policy: GaussianPolicy, offsets: list[tuple[float, float]]
) -> list[float]:
    """Final distances (m) of the global policy's noiseless rollouts (NaN untrained; inf at
    every offset where the batch blew the simulation up)."""
    if not policy.trained:
        return [float("nan")] * len(offsets)
    try:
        return task.sample(
            policy_actor(policy, task.model), offsets, "probe"
        ).scored_distance.tolist()
    except NumericalError:
        return [math.inf] * len(offsets)
