"""Teachers at holes beside a learnt condition's (docs/ALGORITHM.md section 7).

A condition's D_g shows the policy one hole. Beside it, within ``radius``, ``count`` further
holes ``o + r`` (``r`` uniform in the disc, drawn from the condition's seed) each get a teacher
planned on the arm's model, as a new condition's first controller is
(:func:`~lolgps_torch.lolgps.local.planned_controller`), sampled ``samples`` times with its
exploration noise. The successful rollouts, labelled by that teacher (p_cur; no p_pre), join
eq. 8's data as D_g's rows do, and the policy visits those holes in the S-step's closed-loop
rounds as it visits the learnt ones, its states there labelled by the neighbour's teacher
inside its support. A neighbour whose samples all miss gives nothing.
"""

from __future__ import annotations

import math

import torch

from lolgps_torch.controllers import smoothed_noise
from lolgps_torch.errors import NumericalError
from lolgps_torch.lolgps.distillation import Labelled, Labels, label
from lolgps_torch.lolgps.local import (
    LocalConfig,
    Planner,
    initial_controller,
    planned_controller,
)
from lolgps_torch.sim.rollout import linear_gaussian_actor
from lolgps_torch.task import PegTask
from lolgps_torch.types import Trajectories


class Neighbours:
    """Plans and samples the neighbours of a condition (module docstring).

    :param count: neighbours per condition (0: none).
    :param radius: the disc about the condition's hole they are drawn from (m).
    :param samples: rollouts of each neighbour's teacher.
    :param local: the local learners' settings (the plan and its exploration noise).
    :param planner: gives :func:`planned_controller`'s result, computed here or ahead of time
        (:class:`~lolgps_torch.lolgps.plans.PlannedStarts`).
    """

    def __init__(
        self,
        task: PegTask,
        count: int,
        radius: float,
        samples: int,
        local: LocalConfig,
        planner: Planner = planned_controller,
    ) -> None:
        self.task, self.count, self.radius, self.samples = task, count, radius, samples
        self.local, self.planner = local, planner

    def offsets(self, offset: tuple[float, float], seed: int) -> list[tuple[float, float]]:
        """The neighbours' hole offsets: ``count`` points uniform in the disc of ``radius``
        about ``offset`` (``rho = r sqrt(u1)``, ``phi = 2 pi u2``)."""
        gen = torch.Generator().manual_seed(seed)
        u = torch.rand(self.count, 2, generator=gen, dtype=torch.float64)
        rho, phi = self.radius * u[:, 0].sqrt(), 2.0 * math.pi * u[:, 1]
        return [
            (offset[0] + float(r * math.cos(a)), offset[1] + float(r * math.sin(a)))
            for r, a in zip(rho.tolist(), phi.tolist(), strict=True)
        ]

    def __call__(self, offset: tuple[float, float], seed: int) -> tuple[list[Labelled], int]:
        """The neighbours of the hole ``offset`` with their labelled successes (those with
        none left out), and the rollouts drawn."""
        if self.count == 0:
            return [], 0
        task = self.task
        hold = initial_controller(task, self.local)
        gen = torch.Generator().manual_seed(seed + 7919)
        found, rollouts = [], 0
        for hole in self.offsets(offset, seed):
            try:
                p, _ = self.planner(task, task.targets([hole])[0], hold, self.local)
            except NumericalError:
                continue
            noise = smoothed_noise(
                self.samples, task.T, task.layout.dU, self.local.noise_smoothing, gen
            ).to(task.device)
            runs = task.sample(linear_gaussian_actor(p, noise), [hole] * self.samples)
            rollouts += self.samples
            kept = Trajectories(*(f[runs.success] for f in runs))
            if kept.x.shape[0] > 0:
                labels = Labels(p, None, 0)
                found.append(Labelled(hole, label(task, [kept], labels), labels))
        return found, rollouts
