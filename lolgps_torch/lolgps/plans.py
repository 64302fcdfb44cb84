"""Each condition's first controller, planned on the arm's model ahead of time.

The plan (:func:`~lolgps_torch.lolgps.local.planned_controller`) depends on the arm's model,
the hole offset, the hold controller and the learner's settings, not on any sample or on the
policy (except with ``identify``, whose model is re-identified from the rollouts before each
condition). While a condition's S-step runs in this process, the rollout workers wait for
rollouts: :class:`PlannedStarts` has one of them plan the next condition's first controller
meanwhile, with those of its neighbours spread over the workers (:meth:`PlannedStarts.request`),
and hands each to the learner that asks for it (:meth:`PlannedStarts.plan`). The worker runs the same arithmetic on the same model with as
many torch threads as this process, so the plan has the same bits as one made here.

Where that cannot apply, the plan is made in this process when the learner starts, as without
it: no idle worker (one worker, or a CUDA task), identification, the GMM prior or no plan on
the model, a condition other than the one requested (a resumed run's first, say), and any
failure in the worker (a numerical failure then happens again here, and is handled as ever).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from lolgps_torch.lolgps.local import LocalConfig, initial_controller, planned_controller
from lolgps_torch.task import ArmModel, ModelSetup, PegTask
from lolgps_torch.types import LinearGaussian


@functools.lru_cache(maxsize=1)
def arm_model(setup: ModelSetup) -> ArmModel:
    """The model built from ``setup``, once per process while the setup stays the same (a
    worker builds it on its first plan, which runs during an S-step)."""
    return ArmModel(setup)


@dataclass(frozen=True)
class PlanErrand:
    """A condition's first controller planned on a rollout worker (an errand of
    :meth:`~lolgps_torch.sim.pool.RolloutPool.submit`): :func:`planned_controller` on the
    model of ``setup`` at the condition's ``targets [2, 3]``, from ``hold``, with ``config``,
    run with ``threads`` torch threads (those of the process that asked)."""

    setup: ModelSetup
    targets: Tensor
    hold: LinearGaussian
    config: LocalConfig
    threads: int

    def __call__(self) -> tuple[LinearGaussian, float]:
        """The planned controller and the hold's total cost."""
        threads = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        try:
            return planned_controller(arm_model(self.setup), self.targets, self.hold, self.config)
        finally:
            torch.set_num_threads(threads)

    def plans(
        self, task: PegTask, targets: Tensor, hold: LinearGaussian, config: LocalConfig
    ) -> bool:
        """Whether this errand plans what :func:`planned_controller` would at ``task``'s
        current model: the same setup, targets, hold and settings, the model the URDF's."""
        return (
            task.model.dynamics is task.model.urdf
            and task.model_setup() == self.setup
            and config == self.config
            and torch.equal(targets, self.targets)
            and all(torch.equal(a, b) for a, b in zip(hold, self.hold, strict=True))
        )


class PlannedStarts:
    """The first controllers of a stream's conditions (and of their neighbours,
    :mod:`lolgps_torch.lolgps.neighbours`): planned by idle rollout workers when requested
    (:meth:`request`), else in this process.

    :param task: the stream's task; its rollout workers, if any, plan ahead.
    :param config: the local learners' settings.
    """

    def __init__(self, task: PegTask, config: LocalConfig) -> None:
        ahead = config.dynamics.prior == "model" and config.model_plans > 0
        self.task, self.config = task, config
        self.pool = task.pool if ahead and not config.identify else None
        self._pending: list[tuple[PlanErrand, int]] = []  # the errands and their tickets

    def request(self, offsets: Sequence[tuple[float, float]]) -> None:
        """Have the rollout workers plan the first controllers at the holes ``offsets``, in
        turn from the last worker on (nothing without an idle worker). Plans requested
        before and not taken are dropped."""
        if self.pool is None:
            return
        while self._pending:
            self._take(0)
        hold = initial_controller(self.task, self.config)
        for i, offset in enumerate(offsets):
            errand = PlanErrand(
                self.task.model_setup(),
                self.task.targets([offset])[0],
                hold,
                self.config,
                torch.get_num_threads(),
            )
            self._pending.append((errand, self.pool.submit(errand, -1 - i)))

    def plan(
        self, task: PegTask, targets: Tensor, hold: LinearGaussian, config: LocalConfig
    ) -> tuple[LinearGaussian, float]:
        """:func:`planned_controller`'s result: a worker's where a requested plan is this one
        and succeeded, else planned here (a :class:`LocalLearner`'s ``planner``)."""
        for place, (errand, _) in enumerate(self._pending):
            if errand.plans(task, targets, hold, config):
                planned = self._take(place)
                if planned is not None:
                    return planned
                break
        return planned_controller(task, targets, hold, config)

    def _take(self, place: int) -> tuple[LinearGaussian, float] | None:
        """The requested plan at ``place`` among those pending, waited for if the worker is
        still at it (None: the worker failed; then the plan is made here, where a numerical
        failure is handled as ever)."""
        _, ticket = self._pending.pop(place)
        assert self.pool is not None  # plans are requested only with a pool
        try:
            planned: tuple[LinearGaussian, float] = self.pool.collect(ticket)
        except Exception:
            return None
        return planned
