"""The peg-insertion task assembled from its parts: arm, kinematics, placement, worlds, cost.

Conditions are planar hole offsets ``(dx, dy)`` (m) from the nominal hole position.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, get_args

import torch
from torch import Tensor

from lolgps_torch.configs import from_dict
from lolgps_torch.cost.l12 import CostConfig, PegCost
from lolgps_torch.dynamics.identify import TorqueBalance, identify_arm
from lolgps_torch.dynamics.parameters import ArmParameters, IdentifyConfig, identified_dynamics
from lolgps_torch.dynamics.transitions import TransitionStore
from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.effort import check_speeds
from lolgps_torch.robot.ik import solve_ik
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.peg import PegConfig
from lolgps_torch.robot.placement import PlacementConfig, place_task, vertical_peg_targets
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.arm_world import ArmSampler
from lolgps_torch.sim.engines import engine_errors
from lolgps_torch.sim.franka import SIMULATED, RealArmConfig
from lolgps_torch.sim.model import LINK_DAMPING, ControlStep
from lolgps_torch.sim.plant import PlantConfig, believed_plant
from lolgps_torch.sim.pool import RolloutPool, WorldSetup
from lolgps_torch.sim.rollout import Actor, Rollouts, Sampler, rollout_rows
from lolgps_torch.sim.simulator import Simulator, WorldConfig, check_plant, require
from lolgps_torch.types import Trajectories

RolloutKind = Literal["sample", "probe", "visit"]
ROLLOUT_KINDS: tuple[RolloutKind, ...] = get_args(RolloutKind)


@dataclass(frozen=True)
class TaskConfig:
    """Everything that defines the task.  :param urdf: path of the arm's URDF.
    :param ee_link: end-effector link (detected when None).
    :param base_link: the link the arm's chain starts from, every joint above it and off the
        chain held fixed (the root when None: a mobile base's or torso's joints, if any, are
        then part of the chain).
    :param hold: JOINT=VALUE pairs: where held joints stay (rad or m; default 0, or the middle
        of the joint's limits when 0 is outside them).
    :param package_path: folders searched for the ROS packages that ``package://`` mesh URIs
        name, after the URDF's ancestors and ROS_PACKAGE_PATH.
    :param scale: the factor the stream's geometry is scaled by to fit the arm (hole offsets,
        test areas, the start height and an attached peg's length;
        :func:`~lolgps_torch.arm_probes.scaled`); the hole's
        depth and clearances stay as they are.
    :param plant: how the simulated arm departs from the URDF; only the worlds read it.
    :param sim: the simulator that steps the worlds: pybullet, or mujoco (the nominal plant
        only; ``pip install -e '.[mujoco]'``).
    :param mjcf: ``urdf`` names an MJCF file (``--mjcf``), read as the URDF
        :func:`~lolgps_torch.robot.mjcf.mjcf_urdf` makes of it; needs ``sim`` mujoco.
    :param velocity_limit: the joints' velocity limits (rad/s), one for every joint or one per
        actuated joint, in place of the URDF's (or of those derived where it gives none)."""

    urdf: str
    ee_link: str | None = None
    base_link: str | None = None
    hold: tuple[str, ...] = ()
    package_path: tuple[str, ...] = ()
    scale: float = 1.0
    peg: PegConfig = field(default_factory=PegConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    placement: PlacementConfig = field(default_factory=PlacementConfig)
    cost: CostConfig = field(default_factory=CostConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    sim: Simulator = "pybullet"
    mjcf: bool = False
    velocity_limit: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        check_speeds(self.velocity_limit)
        for flag, link in (("--ee-link", self.ee_link), ("--base-link", self.base_link)):
            if link is not None and not link:
                raise LolgpsError(f"{flag} must name a link")
        self.held()  # checks the pairs
        if not (math.isfinite(self.scale) and 0.0 < self.scale <= 1.0):
            raise LolgpsError(f"--scale must be in (0, 1], got {self.scale}")
        for folder in self.package_path:
            if not os.path.isdir(folder):
                raise LolgpsError(f"--package-path {folder}: not a folder")
        parts = (
            ("peg", PegConfig),
            ("world", WorldConfig),
            ("placement", PlacementConfig),
            ("cost", CostConfig),
            ("plant", PlantConfig),
        )
        for name, kind in parts:
            if not isinstance(getattr(self, name), kind):
                raise LolgpsError(f"task {name} settings must be a {kind.__name__}")
        if self.sim not in ("pybullet", "mujoco"):
            raise LolgpsError(f"--sim must be pybullet or mujoco, got {self.sim!r}")
        if self.mjcf and self.sim != "mujoco":
            raise LolgpsError("--mjcf needs --sim mujoco: PyBullet cannot load MJCF")
        check_plant(self.sim, self.plant)
        require(self.sim)

    def held(self) -> dict[str, float]:
        """The ``hold`` pairs as joint -> position; a malformed pair is a :class:`LolgpsError`."""
        held: dict[str, float] = {}
        for pair in self.hold:
            name, sign, text = pair.partition("=")
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not (name and sign and math.isfinite(value)) or name in held:
                raise LolgpsError(
                    f"--hold {pair}: expected JOINT=VALUE, a joint named once and a finite "
                    f"position (rad or m)"
                )
            held[name] = value
        return held


def load_task_arm(config: TaskConfig) -> ArmSpec:
    """The arm of the task ``config`` describes (:func:`~lolgps_torch.robot.arm.load_arm`),
    with the velocity limits it gives."""
    arm = load_arm(
        config.urdf,
        config.ee_link,
        config.peg,
        config.package_path,
        base_link=config.base_link,
        hold=config.held(),
        mjcf=config.mjcf,
    )
    given = config.velocity_limit
    if not given:
        return arm
    if len(given) not in (1, arm.dof):
        raise LolgpsError(
            f"--velocity-limit takes one speed or one per actuated joint ({arm.dof}: "
            f"{', '.join(arm.joint_names)}), got {len(given)}"
        )
    return replace(arm, velocity=given * arm.dof if len(given) == 1 else given)


@dataclass(frozen=True)
class ModelSetup:
    """What a task's model of the arm is built from, as plain data (it pickles, unlike a task,
    whose worlds hold simulator clients): the arm, the world's and the cost's settings, the
    start pose q0 (rad) and the device."""

    arm: ArmSpec
    world: WorldConfig
    cost: CostConfig
    q0: tuple[float, ...]
    device: str = "cpu"


class ArmModel:
    """The parts of a :class:`PegTask` that need no world, built from a :class:`ModelSetup` as
    the task builds its own: the state layout, the episode length T, the start pose q0, the
    kinematics, the cost and the free-space control step of the URDF's arm (``model``)."""

    def __init__(self, setup: ModelSetup) -> None:
        arm, world = setup.arm, setup.world
        self.device = torch.device(setup.device)
        self.layout = world.layout(arm.dof)
        self.T = world.T
        self.q0 = torch.tensor(setup.q0, dtype=torch.float64, device=self.device)
        self.kinematics = PegKinematics(arm, self.device)
        self.cost = PegCost.of(setup.cost, arm, self.kinematics, self.layout)
        self.model = ControlStep(arm, world, device=self.device)


class PegTask:
    """Samples rollouts at hole offsets and scores them with the l12 cost.

    :param n_worlds: worlds of ``sampler``, which steps them in lockstep for callers that batch
        (evaluation, rendering).
    :param workers: processes that :meth:`sample` spreads its rollouts over (1: this process);
        the rollouts are the same for any number. Rollouts on a CUDA device stay in this
        process.
    :param real: the arm the rollouts run on: with a real one (``--arm franka``) they run one
        at a time on it, in this process, whatever ``n_worlds`` and ``workers`` say.
    """

    def __init__(
        self,
        config: TaskConfig,
        n_worlds: int = 5,
        device: str = "cpu",
        workers: int = 1,
        real: RealArmConfig = SIMULATED,
    ) -> None:
        if workers < 1:
            raise LolgpsError(f"workers {workers}: must be at least 1")
        self.config = config
        self.device = torch.device(device)
        self.arm: ArmSpec = load_task_arm(config)
        self.layout = config.world.layout(self.arm.dof)
        self.kinematics = PegKinematics(self.arm, self.device)
        try:  # an arm the loader accepts can still be one no pose or simulation works for
            self.geometry = place_task(
                self.arm, self.kinematics, config.placement, config.world.depth
            )
            mouth, q0 = self.geometry.nominal_mouth, self.geometry.q0
            if real.arm == "simulated":
                self.sampler = Sampler(
                    self.arm, config.world, mouth, q0, n_worlds, device, config.plant, config.sim
                )
            else:
                self.sampler = ArmSampler(
                    real, self.arm, config.world, mouth, q0, device, config.plant
                )
        except (*engine_errors(config.sim), torch.linalg.LinAlgError) as error:
            message = str(error).strip().splitlines()[0] if str(error).strip() else repr(error)
            raise LolgpsError(f"{config.urdf}: the arm cannot be simulated: {message}") from None
        setup = WorldSetup(
            self.arm,
            config.world,
            self.geometry.nominal_mouth,
            self.geometry.q0,
            config.plant,
            config.sim,
        )
        parallel = workers > 1 and self.device.type == "cpu" and real.arm == "simulated"
        self.pool = RolloutPool(setup, workers, self.sampler) if parallel else None
        self._n_worlds, self._simulated = n_worlds, real.arm == "simulated"
        self._model_sampler: Sampler | None = None  # the model's own worlds (:meth:`simulate`)
        self.cost = PegCost.of(config.cost, self.arm, self.kinematics, self.layout)
        self._model: ControlStep | None = None
        self._batches = 0  # batches sampled so far: the key of the next one's sensor noise
        #: the rollouts run on the arm so far, by kind (:meth:`sample`), and those of them its
        #: controller stopped at a limit (the reflex watches every physics step)
        self.arm_rollouts: Counter[RolloutKind] = Counter()
        self.arm_faults: Counter[RolloutKind] = Counter()
        #: the rollouts run on the arm's model instead of the arm (:meth:`simulate`), and those
        #: of them stopped at a limit
        self.model_rollouts = self.model_faults = 0
        #: the free transitions kept for identification (:meth:`record`)
        self.transitions = TransitionStore(
            self.arm, self.layout, config.world.depth, config.world.dt
        )
        self._identified: ArmParameters | None = None  # the arm identified last

    @property
    def model(self) -> ControlStep:
        """The world's free-space control step as a torch function (built on first use)."""
        if self._model is None:
            self._model = ControlStep(self.arm, self.config.world, device=self.device)
        return self._model

    def model_setup(self) -> ModelSetup:
        """What :class:`ArmModel` builds this task's kinematics, cost and URDF model from."""
        q0 = tuple(float(q) for q in self.geometry.q0)
        return ModelSetup(self.arm, self.config.world, self.config.cost, q0, str(self.device))

    def record(self, samples: Trajectories) -> None:
        """Keep the free transitions of ``samples`` for :meth:`identify_model`
        (:meth:`~lolgps_torch.dynamics.transitions.TransitionStore.record`)."""
        self.transitions.record(samples)

    def one_step_errors(self, samples: Trajectories) -> tuple[float, float, float, int]:
        """The root-mean-square joint-velocity error (rad/s) of one control step predicted by
        :attr:`model`, by the URDF's model and by the simulated arm's own
        (:meth:`plant_model`), over the free transitions of ``samples``
        (:func:`~lolgps_torch.dynamics.transitions.free_transitions`), and how many there are
        (NaN errors where none)."""
        x, free = self.transitions.free(samples)
        before, after, u = x[:, :-1][free], x[:, 1:][free], samples.u[free]
        if before.shape[0] == 0:
            return math.nan, math.nan, math.nan, 0
        qd = self.layout.qd
        urdf = ControlStep(self.arm, self.config.world, device=self.device)
        with torch.no_grad():
            errors = [
                float((model(before, u)[:, qd] - after[:, qd]).square().mean().sqrt())
                for model in (self.model, urdf, self.plant_model())
            ]
        return errors[0], errors[1], errors[2], int(before.shape[0])

    def plant_model(self) -> ControlStep:
        """The control step of the arm as the simulator has it (:meth:`World.plant_urdf
        <lolgps_torch.sim.simulator.World.plant_urdf>`: the plant's link masses, inertias and
        payload) under the gravity compensation the
        plant and the learner apply: the model built from the true plant, which an identified
        one can at best match (joint friction, sensor noise and an unknown delay left out, as
        in every model here; an arm compensated by itself and by the learner too is modelled
        with twice its own gravity)."""
        plant, learner = self.config.plant, float(self.config.world.compensate_gravity)
        simulated = replace(self.arm, urdf_text=self.sampler.worlds[0].plant_urdf())
        exact = ControlStep(simulated, self.config.world, self.device)
        if plant.gravity_compensation == "plant":  # the simulated body's own gravity
            own = (exact.urdf, 1.0 + learner, 0.0)
            return ControlStep(simulated, self.config.world, self.device, own)
        kappa = float(plant.gravity_compensation == "model") + learner  # the URDF's
        return ControlStep(self.arm, self.config.world, self.device, (exact.urdf, kappa, 0.0))

    def identify_model(self, config: IdentifyConfig) -> ArmParameters | None:
        """Identify the arm from the transitions :meth:`record` kept and make :attr:`model` the
        identified arm's (:func:`~lolgps_torch.dynamics.identify.identify_arm`; None, the
        model unchanged, before any transition, or with a warning where it is kept). With a
        known delay (``WorldConfig.known_delay``) each physics step of a transition is driven
        by the command that :class:`ControlStep` has act there, from the state's action
        history; an arm late by a delay the learner does not know is identified as one whose
        commands act at once (:mod:`lolgps_torch.dynamics.identify`)."""
        data = self.transitions.data
        if data is None:
            return None
        step = ControlStep(self.arm, self.config.world, device=self.device)
        urdf, world = step.urdf, self.config.world
        effort = torch.tensor(self.arm.effort, dtype=torch.float64, device=self.device)
        # each physics step driven by the command the known delay makes act there
        balance = TorqueBalance(
            urdf, effort, world.dt, LINK_DAMPING, world.substeps, tuple(step.late)
        )
        params = identify_arm(balance, data, config, self._identified)
        if params is None:
            return None
        self._identified = params
        identified = (
            identified_dynamics(urdf, params),
            float(params.compensation),
            float(params.own),
        )
        self._model = ControlStep(self.arm, self.config.world, self.device, identified)
        return params

    @property
    def T(self) -> int:
        return self.config.world.T

    @property
    def q0(self) -> Tensor:
        return torch.tensor(self.geometry.q0, dtype=torch.float64, device=self.device)

    def targets(self, offsets: Sequence[tuple[float, float]]) -> Tensor:
        """Tip and top targets ``[M, 2, 3]`` for hole offsets ``[M, 2]``."""
        mouth = torch.tensor(self.geometry.nominal_mouth, dtype=torch.float64, device=self.device)
        off = torch.tensor(offsets, dtype=torch.float64, device=self.device).reshape(-1, 2)
        tip = mouth + torch.nn.functional.pad(off, (0, 1))
        tip[:, 2] -= self.config.world.depth
        return vertical_peg_targets(tip, -self.arm.point_offsets[1][2])

    def check_reachable(self, offset: tuple[float, float]) -> None:
        """Raise :class:`LolgpsError` if the peg cannot be inserted at this hole offset."""
        targets = self.targets([offset])[0]
        _, err = solve_ik(self.kinematics, self.arm, targets, margin=0.0)
        if err > self.config.placement.ik_tolerance:
            raise LolgpsError(
                f"hole offset ({offset[0]:+.3f}, {offset[1]:+.3f}) m is out of the arm's reach "
                f"(best inverse-kinematics error {float(err):.3f} m)"
            )

    def effective_inertia(self) -> Tensor:
        """``1 / diag(M(q0)^{-1})`` per actuated joint (kg m^2): the inertia each joint feels,
        in the URDF's arm (not the plant's)."""
        world = self.sampler.worlds[0]
        return world.effective_inertia(self.geometry.q0).to(self.device)

    def joint_damping(self) -> Tensor:
        """The joint damping b (N m s/rad) of the URDF, per actuated joint."""
        return self.sampler.worlds[0].joint_damping().to(self.device)

    def sample(
        self, act: Actor, offsets: Sequence[tuple[float, float]], kind: RolloutKind = "sample"
    ) -> Trajectories:
        """One rollout per offset, each run alone (on the worker processes, if any), scored by
        the cost; each call's sensor noise is new. The rollouts are counted in
        :attr:`arm_rollouts` as ``kind``: a local controller's ``sample``, a ``probe`` (a
        controller's or the policy's noiseless check) or a ``visit`` of the policy in the
        S-step; those the arm's controller stopped at a limit in :attr:`arm_faults`."""
        self.arm_rollouts[kind] += len(offsets)
        rolled = self._roll(act, offsets, self.sampler, self.pool)
        self.arm_faults[kind] += int(rolled.fault.sum())
        return self.score(rolled, offsets)

    def simulate(self, act: Actor, offsets: Sequence[tuple[float, float]]) -> Trajectories:
        """:meth:`sample` on the arm's model instead of the arm (its description as the learner
        believes it, :func:`~lolgps_torch.sim.plant.believed_plant`), counted apart
        (:attr:`model_rollouts`, :attr:`model_faults`): on the task's worlds where they are that
        model, else (a real arm, a plant unlike its description) on its own, in this process."""
        world = self.config.world
        believed = believed_plant(
            world.compensate_gravity, world.known_delay, self.config.plant.limits
        )
        self.model_rollouts += len(offsets)
        if self._simulated and self.config.plant == believed:
            rolled = self._roll(act, offsets, self.sampler, self.pool)
        else:
            if self._model_sampler is None:
                mouth, q0 = self.geometry.nominal_mouth, self.geometry.q0
                self._model_sampler = Sampler(
                    self.arm, world, mouth, q0, self._n_worlds, self.device, believed,
                    self.config.sim,
                )  # fmt: skip
            rolled = self._roll(act, offsets, self._model_sampler, None)
        self.model_faults += int(rolled.fault.sum())
        return self.score(rolled, offsets)

    def _roll(
        self,
        act: Actor,
        offsets: Sequence[tuple[float, float]],
        sampler: Sampler,
        pool: RolloutPool | None,
    ) -> Rollouts:
        """One batch of rollouts on ``sampler``'s worlds, or on ``pool``'s workers; each
        batch's sensor noise is new."""
        batch, self._batches = self._batches, self._batches + 1
        if pool is None:
            return rollout_rows(sampler, act, offsets, range(len(offsets)), batch)
        return Rollouts(*(part.to(self.device) for part in pool.rollout(act, offsets, batch)))

    def arm_seconds(self) -> float | None:
        """A real arm's seconds so far under torque command and moving to the start pose
        (None in a simulator)."""
        return self.sampler.seconds() if isinstance(self.sampler, ArmSampler) else None

    def score(self, rolled: Rollouts, offsets: Sequence[tuple[float, float]]) -> Trajectories:
        """Rollouts (``x: [N, T+1, dX]``, ``x_T`` after the last action) at the hole
        ``offsets``, with their per-step cost ``l(x_t, u_t)`` and success
        (``final < success_threshold``, and no fault)."""
        x, u, final, fault = rolled
        cost = self.cost.evaluate(x[:, :-1], u, self.targets(offsets)[:, None])
        success = (final < self.config.world.success_threshold) & ~fault
        return Trajectories(x[:, :-1], u, cost, final, success, x[:, -1], fault)

    def close(self) -> None:
        self.sampler.close()
        if self._model_sampler is not None:
            self._model_sampler.close()
        if self.pool is not None:
            self.pool.close()


def task_config_from_dict(d: dict[str, Any]) -> TaskConfig:
    """Inverse of ``dataclasses.asdict`` for :class:`TaskConfig` (as saved in config.json,
    where ``urdf_sha256`` records the hash of the run folder's URDF copy beside it)."""
    return from_dict(TaskConfig, {k: v for k, v in d.items() if k != "urdf_sha256"})
