"""Each condition's first controller, planned on the arm's model ahead of time.

The plan (:func:`~lolgps_torch.lolgps.local.planned_controller`) depends on the arm's model,
the hole offset, the hold controller and the learner's settings, not on any sample or on the
policy (except with ``identify``, whose model is re-identified from the rollouts before each
condition). While a condition's S-step runs in this process, the rollout workers wait for
rollouts: :class:`PlannedStarts` has one of them plan the next condition's first controller
meanwhile (:meth:`PlannedStarts.request`) and hands it to that condition's learner
(:meth:`PlannedStarts.plan`). The worker runs the same arithmetic on the same model with as
many torch threads as this process, so the plan has the same bits as one made here.

Where that cannot apply, the plan is made in this process when the learner starts, as without
it: no idle worker (one worker, or a CUDA task), identification, the GMM prior or no plan on
the model, a condition other than the one requested (a resumed run's first, say), and any
failure in the worker (a numerical failure then happens again here, and is handled as ever).
"""

from __future__ import annotations

import functools
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
    """The first controller of each condition of a stream: planned by an idle rollout worker
    when the condition was requested (:meth:`request`), else in this process.

    :param task: the stream's task; its rollout workers, if any, plan ahead.
    :param config: the local learners' settings.
    """

    def __init__(self, task: PegTask, config: LocalConfig) -> None:
        ahead = config.model_plans > 0
        self.task, self.config = task, config
        self.pool = task.pool if ahead and not config.identify else None
        self._pending: tuple[PlanErrand, int] | None = None  # the errand and its ticket

    def request(self, offset: tuple[float, float] | None) -> None:
        """Have a rollout worker plan the first controller at the hole ``offset`` (nothing
        without an idle worker, or for None)."""
        if self.pool is None or offset is None:
            return
        self._take()  # a plan requested but not taken
        errand = PlanErrand(
            self.task.model_setup(),
            self.task.targets([offset])[0],
            initial_controller(self.task, self.config),
            self.config,
            torch.get_num_threads(),
        )
        self._pending = (errand, self.pool.submit(errand))

    def plan(
        self, task: PegTask, targets: Tensor, hold: LinearGaussian, config: LocalConfig
    ) -> tuple[LinearGaussian, float]:
        """:func:`planned_controller`'s result: the worker's where the requested plan is this
        one and succeeded, else planned here (a :class:`LocalLearner`'s ``planner``)."""
        pending, planned = self._pending, self._take()
        if (
            pending is not None
            and planned is not None
            and pending[0].plans(task, targets, hold, config)
        ):
            return planned
        return planned_controller(task, targets, hold, config)

    def _take(self) -> tuple[LinearGaussian, float] | None:
        """The requested plan, waited for if the worker is still at it (None: none requested,
        or the worker failed; then the plan is made here, where a numerical failure is handled
        as ever)."""
        pending, self._pending = self._pending, None
        if pending is None or self.pool is None:
            return None
        try:
            planned: tuple[LinearGaussian, float] = self.pool.collect(pending[1])
        except Exception:
            return None
        return planned
