"""The rollout side of the evaluation: noiseless rollouts of checkpointed global policies.

The main process builds the full :class:`~lolgps_torch.task.PegTask`, loads the checkpoints
and scores every rollout; a spawned worker only steps physics and runs the policies. It
receives the main task's arm, world settings and geometry and the policies' weights as plain
data (:class:`RolloutSetup`), builds its own worlds (a PyBullet client cannot be pickled) and
returns states, actions and final tip distances; it reads no files. So that its start-up stays
short, this module imports neither pytorch_kinematics nor yourdfpy/trimesh, directly or
through the modules it uses.
"""

from __future__ import annotations

import multiprocessing.queues
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.sharedctypes import Synchronized
from typing import Any, NamedTuple

import numpy as np
import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy.actor import policy_actor
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.model import ControlStep
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.rollout import Sampler
from lolgps_torch.sim.simulator import Simulator, WorldConfig

Position = tuple[float, float]


class Job(NamedTuple):
    """One batch of rollouts: the index of a policy in :attr:`RolloutSetup.policies` and the
    hole offsets to run it at."""

    policy: int
    positions: tuple[Position, ...]


class PolicyState(NamedTuple):
    """A global policy as plain data: its name (for messages), its
    :meth:`GaussianPolicy.description` and its state dict as arrays."""

    name: str
    description: dict[str, Any]
    state: dict[str, np.ndarray]

    @classmethod
    def of(cls, name: str, policy: GaussianPolicy) -> PolicyState:
        state = {key: value.detach().cpu().numpy() for key, value in policy.state_dict().items()}
        return cls(name, policy.description(), state)

    def build(self) -> GaussianPolicy:
        state = {key: torch.from_numpy(value) for key, value in self.state.items()}
        return GaussianPolicy.from_state(self.description, state)


class Rollouts(NamedTuple):
    """The rollouts of a :class:`Job`, one per position, as float64 arrays: states x
    ``[N, T, dX]``, actions u ``[N, T, dU]``, final tip distances ``[N]`` (m) and faults
    ``[N]`` (bool: the arm's controller stopped the rollout at a limit)."""

    x: np.ndarray
    u: np.ndarray
    final_distance: np.ndarray
    fault: np.ndarray


class Failure(NamedTuple):
    """A worker's exception, as plain data: a user error's message or a bug's traceback."""

    user_error: bool
    message: str


@dataclass(frozen=True)
class RolloutSetup:
    """What a worker needs to build worlds identical to the main task's.

    :param arm: the task's arm (``PegTask.arm``).
    :param world: simulation and hole settings (``TaskConfig.world``).
    :param nominal_mouth: the nominal hole mouth (m) from the task's placement.
    :param q0: the start pose (rad) from the task's placement.
    :param n_worlds: worlds stepped in lockstep (the batch size).
    :param policies: the policies the jobs run.
    :param plant: the simulated arm (``TaskConfig.plant``).
    :param simulator: the simulator that steps the worlds (``TaskConfig.sim``).
    """

    arm: ArmSpec
    world: WorldConfig
    nominal_mouth: tuple[float, float, float]
    q0: tuple[float, ...]
    n_worlds: int
    policies: tuple[PolicyState, ...]
    plant: PlantConfig = NOMINAL_PLANT
    simulator: Simulator = "pybullet"

    def sampler(self) -> Sampler:
        """A new pool of ``n_worlds`` worlds in this process."""
        return Sampler(
            self.arm,
            self.world,
            self.nominal_mouth,
            self.q0,
            self.n_worlds,
            plant=self.plant,
            simulator=self.simulator,
        )


class PolicyRoller:
    """Noiseless rollouts (``u_t = mu_theta(x_t)``) of global policies in the worlds of
    ``sampler``, whose states and actions are laid out as ``model``'s, the arm's model the
    policies' guards brake and predict by; a policy of other sizes is a :class:`LolgpsError`. The
    sampler stays its owner's to close."""

    def __init__(
        self, sampler: Sampler, model: ControlStep, policies: Sequence[PolicyState]
    ) -> None:
        self.sampler, self.model, layout = sampler, model, model.layout
        self.policies = [state.build().eval() for state in policies]
        for state, policy in zip(policies, self.policies, strict=True):
            if (policy.dX, policy.dU) != (layout.dX, layout.dU):
                raise LolgpsError(
                    f"{state.name}: policy maps {policy.dX} -> {policy.dU} dims, the run's task "
                    f"has states of {layout.dX} and actions of {layout.dU}"
                )

    def __call__(self, job: Job) -> Rollouts:
        """One rollout per position of ``job``."""
        actor = policy_actor(self.policies[job.policy], self.model)
        return Rollouts(*(a.numpy() for a in self.sampler.rollout(actor, list(job.positions))))


class SetupRoller:
    """A :class:`PolicyRoller` in worlds it builds from a :class:`RolloutSetup`, on one torch
    thread: the state of one Ray actor of the evaluation (its worlds live as long as it)."""

    def __init__(self, setup: RolloutSetup) -> None:
        torch.set_num_threads(1)
        self.roller = PolicyRoller(
            setup.sampler(), ControlStep(setup.arm, setup.world), setup.policies
        )

    def roll(self, index: int, job: Job) -> tuple[int, Rollouts]:
        """``(index, rollouts of job)``."""
        return index, self.roller(job)


def next_job(counter: Synchronized[int], n_jobs: int) -> int | None:
    """Claim the next unclaimed job index from the shared counter (None: all claimed)."""
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    return index if index < n_jobs else None


def run_worker(
    setups: multiprocessing.queues.Queue[RolloutSetup],
    jobs: list[Job],
    counter: Synchronized[int],
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]],
) -> None:
    """A worker process: wait for the main process's :class:`RolloutSetup`, build its worlds,
    then run jobs until all are claimed, putting ``(job index, rollouts)`` on ``results``; an
    exception ends it as ``(-1, Failure)``."""
    torch.set_num_threads(1)
    try:
        setup = setups.get()
        roller = PolicyRoller(setup.sampler(), ControlStep(setup.arm, setup.world), setup.policies)
        while (index := next_job(counter, len(jobs))) is not None:
            results.put((index, roller(jobs[index])))
    except LolgpsError as error:
        results.put((-1, Failure(True, str(error))))
    except Exception:  # a bug: its traceback goes to the parent, which raises it
        results.put((-1, Failure(False, traceback.format_exc())))
