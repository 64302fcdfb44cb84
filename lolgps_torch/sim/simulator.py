"""The simulator seam: what the task, the samplers, evaluation and rendering ask of a simulated
world, whichever engine steps it (``TaskConfig.sim``: ``pybullet``, the default, or
``mujoco``).

- :class:`WorldConfig`: the world's settings, the same for every engine.
- :class:`World`: one world with the arm, the table and the funnel hole. Its public methods are
  the interface (``set_hole``, ``reset``, ``step``, ``observe``, ``points``, ``tip_distance``,
  ``effective_inertia``, ``joint_damping``, ``plant_urdf``, ``close``); it holds everything that does not
  depend on the engine (the state vector, the command queue of a delayed plant, the sensor
  noise, the effort limits), and an engine supplies a few primitives: move the hole, set the
  joints, read them, the point frame's pose, the gravity compensation and one physics step.
- :class:`Display`: a world posed from recorded joint angles and photographed, for videos.
- :func:`~lolgps_torch.sim.engines.build_world`, :func:`~lolgps_torch.sim.engines.build_display`
  and :func:`~lolgps_torch.sim.engines.engine_errors` pick the engine by name; each engine's
  module is imported only when it is asked for.

The geometry both engines build is described once in :mod:`lolgps_torch.sim.geometry`, the
reflex that stops the arm at its limits in :mod:`lolgps_torch.sim.reflex`.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import math
import re
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple, Protocol

import numpy as np
import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.plant import (
    NOMINAL_PLANT,
    VELOCITY_NOISE_RATIO,
    PlantConfig,
)
from lolgps_torch.sim.reflex import Reflex
from lolgps_torch.state import StateLayout

Simulator = Literal["pybullet", "mujoco"]
MUJOCO_INSTALL = "pip install -e '.[mujoco]'"
MUJOCO_OLDEST = (3, 3, 7)
# a MuJoCo of another release, or a 4.x upgraded in place over a 3.x (4.0 split the package)
MUJOCO_REINSTALL = f"pip uninstall -y mujoco && {MUJOCO_INSTALL}"


@dataclass(frozen=True)
class WorldConfig:
    """Simulation and hole geometry (SI units).

    :param dt: control step. :param substeps: physics steps per control step.
    :param T: steps per episode. :param gravity: gravitational acceleration (m/s^2).
    :param depth: hole depth. :param clearance_mouth: clearance per side at the mouth.
    :param clearance_bottom: clearance per side at the floor.
    :param plate_thickness: guide plate thickness. :param table_half_size: table half extent.
    :param friction: lateral friction of table and hole.
    :param success_threshold: tip-to-target distance that counts as inserted.
    :param damping_margin: joints whose effective inertia is below ``damping_margin * b * dt``
        (b the URDF joint damping, dt the physics step) get rotor-like inertia added, since
        PyBullet's explicit joint damping is unstable there (pybullet_data's xArm, damping 1,
        drifted 7 rad in 5 s with zero action before this).
    :param max_joint_speed: joint speed (rad/s) beyond which a state counts as a simulator
        blow-up (PyBullet itself caps joint speeds at 100 rad/s by default).
    :param known_delay: the command delay (s) the learner allows for, to the nearest physics
        step (dt / substeps): the state carries the actions of the last ceil(d / dt) control steps and the arm's model
        acts on each command d late (set it to the arm's latency)
    :param compensate_gravity: the learner adds its own model's gravity torque
        ``g_URDF(q)`` (the URDF's rigid-body inverse dynamics at rest, at the observed joint
        angles) to every command it sends, for an arm that does not compensate gravity itself
    """

    dt: float = 0.05
    substeps: int = 5
    T: int = 100
    gravity: float = 9.81
    depth: float = 0.10
    clearance_mouth: float = 0.004
    clearance_bottom: float = 0.001
    plate_thickness: float = 0.02
    table_half_size: float = 0.6
    friction: float = 0.2
    success_threshold: float = 0.06
    damping_margin: float = 1.0
    max_joint_speed: float = 100.0
    known_delay: float = 0.0
    compensate_gravity: bool = False

    def __post_init__(self) -> None:
        positive = {
            "dt": self.dt,
            "gravity": self.gravity,
            "depth": self.depth,
            "clearance_mouth": self.clearance_mouth,
            "clearance_bottom": self.clearance_bottom,
            "plate_thickness": self.plate_thickness,
            "table_half_size": self.table_half_size,
            "success_threshold": self.success_threshold,
            "max_joint_speed": self.max_joint_speed,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise LolgpsError(f"world {name} must be positive and finite, got {value}")
        for name, value in (("friction", self.friction), ("damping_margin", self.damping_margin)):
            if not (math.isfinite(value) and value >= 0):
                raise LolgpsError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        if self.substeps < 1 or self.T < 1:
            raise LolgpsError(
                f"world substeps and T must be at least 1, got {self.substeps}, {self.T}"
            )
        if self.clearance_bottom > self.clearance_mouth:
            raise LolgpsError(
                f"the hole's clearance at the floor ({self.clearance_bottom} m) exceeds that "
                f"at the mouth ({self.clearance_mouth} m)"
            )
        if not (math.isfinite(self.known_delay) and self.known_delay >= 0):
            raise LolgpsError(f"--known-delay must be >= 0 and finite, got {self.known_delay}")

    @property
    def delay_steps(self) -> int:
        """The known delay in physics steps, to the nearest."""
        return round(self.known_delay * self.substeps / self.dt)

    @property
    def history(self) -> int:
        """Actions kept in the state: ``ceil(d / dt)`` for the known delay d."""
        return -(-self.delay_steps // self.substeps)

    def layout(self, dof: int) -> StateLayout:
        """The state vector's layout for an arm of ``dof`` actuated joints."""
        return StateLayout(dof, self.history)


class World(ABC):
    """One world with the arm, the table and the hole, stepped by an engine (module
    docstring).  Not picklable: build it in the process that uses it.

    Dynamics: each control step of ``dt`` holds the command for ``substeps`` physics steps.
    The joint torque sent at every physics step is ``clip(u + g(q), -effort, effort)``, where
    ``g(q)`` is the gravity-compensation torque (inverse dynamics at zero velocity and
    acceleration) evaluated at the start of the control step, as a torque-controlled arm's own
    gravity compensation would.  With ``WorldConfig.compensate_gravity`` the learner adds its
    own model's ``g_URDF(q~)`` (:meth:`learner_compensation`, at the observed angles ``q~``)
    to every command as it is issued, so the torque is ``clip(u + g_URDF(q~) + g(q), ...)``,
    ``u`` still a torque over model-based compensation.  Only the peg collides with the table
    and the hole.

    :param arm: the arm. :param config: simulation and hole geometry.
    :param nominal_mouth: the hole's mouth at offset zero (world, m).
    :param plant: how the simulated arm departs from its URDF.
    """

    #: whether a batch's rollouts run together (:meth:`step_together`, and actors that act on
    #: each row alone, :class:`~lolgps_torch.sim.rollout.Rowwise`) rather than one at a time:
    #: an engine whose step costs mostly Python, not physics, gains from it
    lockstep: bool = False

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        plant: PlantConfig = NOMINAL_PLANT,
    ) -> None:
        self.arm, self.config, self.plant = arm, config, plant
        self.layout = config.layout(arm.dof)
        self.nominal_mouth = np.asarray(nominal_mouth, dtype=np.float64)
        self.delay, self.delay_fraction = plant.delay_steps(config.dt / config.substeps)
        self.offsets = np.asarray(arm.point_offsets, dtype=np.float64)  # [2, 3]
        self.effort = np.asarray(arm.effort, dtype=np.float64)
        self.targets = np.zeros((2, 3))
        self._prev_points = np.zeros(6)
        self._points = np.zeros(6)
        # commands issued, not yet acting (one more where a physics step mixes two)
        self._queue = np.zeros((self.delay + (self.delay_fraction > 0), arm.dof))
        self._issued = np.zeros((config.history, arm.dof))  # the last commands, newest first
        self._noise: np.random.Generator | None = None
        self._observed_q = np.zeros(arm.dof)  # the joint angles the last observation gave
        self._model: ArmDynamics | None = None  # the learner's, built when first needed
        self.reflex = Reflex.of(arm) if plant.limits == "reflex" else None
        #: why the arm's controller stopped the rollout (one line), None while the arm runs;
        #: once set, :meth:`step` leaves the arm braked where it stopped until :meth:`reset`
        self.fault: str | None = None
        self._steps = 0  # control steps since the last reset

    # the engine's primitives

    @abstractmethod
    def _move_hole(self, mouth: np.ndarray) -> None:
        """Put the hole's frame (the mouth's centre) at ``mouth`` (world, m)."""

    @abstractmethod
    def _set_joints(self, q: np.ndarray) -> None:
        """Put the actuated joints at ``q``, at rest."""

    @abstractmethod
    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The actuated joints' angles and velocities now, ``([dof], [dof])``."""

    @abstractmethod
    def _point_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The point frame's world position ``[3]`` and rotation ``[3, 3]`` now."""

    @abstractmethod
    def _physics_step(self, tau: np.ndarray) -> None:
        """One physics step of ``dt / substeps`` with the joint torques ``tau: [dof]``."""

    @abstractmethod
    def gravity_compensation(self) -> np.ndarray:
        """``g(q) [dof]`` at the joint angles the last observation read, as the plant
        computes it."""

    @abstractmethod
    def effective_inertia(self, q: Sequence[float]) -> Tensor:
        """``1 / diag(M(q)^{-1})`` per actuated joint (kg m^2, float64): the inertia each joint
        feels at ``q``, in the URDF's arm (not the plant's)."""

    @abstractmethod
    def joint_damping(self) -> Tensor:
        """The joint damping b (N m s/rad, float64) of the URDF, per actuated joint."""

    @abstractmethod
    def close(self) -> None:
        """Release the engine's resources."""

    def plant_urdf(self) -> str:
        """The URDF of the arm as simulated: the arm's own, unless the engine simulates a
        plant that departs from it (:meth:`PegWorld.plant_urdf
        <lolgps_torch.sim.world.PegWorld.plant_urdf>`)."""
        return self.arm.urdf_text

    # the interface, the same for every engine

    def set_hole(self, offset: tuple[float, float]) -> None:
        """Move the hole to ``nominal + (dx, dy)``; targets: tip at the floor centre, top above."""
        mouth = self.nominal_mouth + np.array([offset[0], offset[1], 0.0])
        self._move_hole(mouth)
        tip = mouth - np.array([0.0, 0.0, self.config.depth])
        self.targets = np.stack([tip, tip - self.offsets[1]])  # top offset points down the axis

    def points(self) -> np.ndarray:
        """World positions of the tip and top points, ``[2, 3]``."""
        position, R = self._point_pose()
        return position + self.offsets @ R.T

    def reset(self, q0: np.ndarray, key: tuple[int, ...] = (0,)) -> np.ndarray:
        """Put the arm at rest at ``q0``, with no command pending, and return the state; the
        rollout's sensor noise is drawn from ``key`` (:meth:`PlantConfig.noise`)."""
        self._set_joints(np.asarray(q0, dtype=np.float64))
        self.fault, self._steps = None, 0
        self._queue = np.zeros_like(self._queue)
        self._issued = np.zeros_like(self._issued)
        self._noise = self.plant.noise(key)
        self._prev_points = (self.points() - self.targets).reshape(6)
        return self.observe()  # zero point velocity at rest

    def observe(self) -> np.ndarray:
        """The state vector ``[dX]`` (see :class:`StateLayout`)."""
        q, qd = self._joint_state()
        if not (np.isfinite(q).all() and np.abs(qd).max() <= self.config.max_joint_speed):
            raise NumericalError(
                f"the simulation blew up: joint speed {np.abs(qd).max():.3g} rad/s "
                f"(bound {self.config.max_joint_speed:g})"
            )
        pts = (self.points() - self.targets).reshape(6)
        vel = (pts - self._prev_points) / self.config.dt
        self._points = pts
        if self._noise is not None:
            scale = self.plant.obs_noise
            q = q + self._noise.normal(0.0, scale, q.shape)
            qd = qd + self._noise.normal(0.0, VELOCITY_NOISE_RATIO * scale, qd.shape)
        self._observed_q = q
        return np.concatenate([q, qd, pts, vel, self._issued.reshape(-1)])

    def step(self, u: np.ndarray) -> np.ndarray:
        """Issue torque ``u`` (on top of gravity compensation) for one control step, starting
        from the state the last :meth:`reset`, :meth:`observe` or :meth:`step` returned; with a
        delay of d physics steps, the commands issued d steps earlier act instead (over a
        step that a fractional delay splits, the mean of the two, :meth:`PlantConfig.delay_steps
        <lolgps_torch.sim.plant.PlantConfig.delay_steps>`). Where the arm passes a limit
        (:class:`Reflex`) it is braked, and stays so (:attr:`fault`)."""
        for tau in self._command(u):
            self._physics_step(tau)
            if self.check_limits():
                break
        self._steps += 1
        return self.observe()

    def check_limits(self) -> bool:
        """Whether the arm's controller has stopped the arm: at the joint state now, a joint
        past its velocity limit or within :data:`~lolgps_torch.sim.reflex.POSITION_MARGIN` of
        a position limit (:class:`Reflex`) brakes it to rest where it is and sets
        :attr:`fault`; with the limits off, never."""
        if self.reflex is None or self.fault is not None:
            return self.fault is not None
        q, qd = self._joint_state()
        self.fault = self.reflex.violation(q, qd, self._steps)
        if self.fault is not None:
            self._set_joints(q)
        return self.fault is not None

    def _command(self, u: np.ndarray) -> np.ndarray:
        """The book-keeping of a control step issuing ``u`` (:meth:`step`), and the joint
        torques of its physics steps, ``[substeps, dof]`` (none, ``[0, dof]``, once the arm is
        braked: it does not move)."""
        substeps = self.config.substeps
        if self.fault is not None:
            self._prev_points = self._points
            return np.empty((0, len(u)))
        if not np.isfinite(u).all():
            raise NumericalError("non-finite action: the controller produced NaN or inf torques")
        g = self.gravity_compensation()
        if self.config.compensate_gravity:  # the learner's own, sent with the command
            own = self.learner_compensation()
            sent, g_total = u + own, g + own
        else:
            sent, g_total = u, g
        late = len(self._queue)
        held = np.empty((late + substeps, len(u)))
        held[:late] = self._queue
        held[late:] = sent
        self._queue = held[substeps:]
        if self.delay_fraction > 0:  # row j + 1 is k physics steps late at step j, row j k + 1
            f = self.delay_fraction
            held = (1.0 - f) * held[1:] + f * held[:-1]
        if len(self._issued):  # the state keeps the last commands
            # the commands as they act (within the effort limits): past commands beyond them
            # would grow without bound under a controller that feeds them back
            acting = np.clip(u + g_total, -self.effort, self.effort) - g_total
            self._issued = np.concatenate([acting[None], self._issued])[: len(self._issued)]
        self._prev_points = self._points
        return np.clip(held[:substeps] + g, -self.effort, self.effort)

    def learner_compensation(self) -> np.ndarray:
        """``g_URDF(q~) [dof]``: the gravity torque of the learner's rigid-body model of the
        arm (:class:`~lolgps_torch.robot.rigid_body.ArmDynamics`, the URDF as PyBullet loads
        it), ``RNEA(q~, 0, 0)`` at the joint angles ``q~`` the last observation gave (sensor
        noise included): what the learner adds to its commands with
        ``WorldConfig.compensate_gravity``.  The plant's parameters are not read."""
        if self._model is None:
            self._model = ArmDynamics(self.arm, self.config.gravity, "pybullet")
        q = torch.from_numpy(np.asarray(self._observed_q, dtype=np.float64))
        return self._model.gravity_torque(q).numpy()

    @classmethod
    def step_together(cls, worlds: Sequence[World], u: np.ndarray) -> np.ndarray:
        """:meth:`step` of each of ``worlds`` (of this engine) with its row of ``u: [n, dU]``;
        the states ``[n, dX]``.  Each world's state is what its own :meth:`step` returns: an
        engine may take the worlds' physics steps together, never mixing their numbers."""
        return np.stack([world.step(row) for world, row in zip(worlds, u, strict=True)])

    def tip_distance(self) -> float:
        """Distance (m) from the peg tip to the hole-floor target."""
        return float(np.linalg.norm(self.points()[0] - self.targets[0]))


class Camera(NamedTuple):
    """A pinhole camera looking at ``target`` from ``eye`` (world, m), ``fov`` degrees."""

    eye: np.ndarray
    target: np.ndarray
    fov: float


class Display(Protocol):
    """A world for pictures: the arm and a coloured copy of its hole, posed (no physics runs)
    and photographed."""

    @property
    def world(self) -> World:
        """The posed world (its ``nominal_mouth`` and ``points``)."""

    def show(self, offset: tuple[float, float], q: np.ndarray) -> None:
        """Put the hole at ``offset`` and the arm at joint angles ``q``, at rest."""

    def photograph(self, camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The current pose through ``camera``: RGB ``[H, W, 3]`` uint8, and a segmentation
        ``[H, W]`` (int, negative for the background) that :meth:`peg_mask` reads."""

    def peg_mask(self, segmentation: np.ndarray) -> np.ndarray:
        """Where a segmentation of :meth:`photograph` shows the peg, ``[H, W]`` bool."""

    def close(self) -> None:
        """Release the display's resources."""


def require(simulator: Simulator) -> None:
    """Raise :class:`LolgpsError` if ``simulator``'s engine is not installed (PyBullet always
    is; MuJoCo is the ``mujoco`` extra: a release from :data:`MUJOCO_OLDEST` up to 4.x, but
    not 4.0.0, whose Newton solver 4.0.1 corrected), or does not import."""
    if simulator != "mujoco":
        return
    if importlib.util.find_spec("mujoco") is None:
        raise LolgpsError(f"--sim mujoco needs MuJoCo, which is not installed: {MUJOCO_INSTALL}")
    version = importlib.metadata.version("mujoco")
    release = tuple(int(part) for part in re.findall(r"\d+", version)[:3])
    if not MUJOCO_OLDEST <= release < (5,) or release == (4, 0, 0):
        raise LolgpsError(
            f"--sim mujoco needs MuJoCo 3.3.7 up to 4.x (not 4.0.0), found {version}: "
            f"{MUJOCO_REINSTALL}"
        )
    try:
        importlib.import_module("mujoco")
    except ImportError as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else repr(error)
        raise LolgpsError(
            f"MuJoCo {version} is installed but does not import ({first}): {MUJOCO_REINSTALL}"
        ) from None


def check_plant(simulator: Simulator, plant: PlantConfig) -> None:
    """Raise :class:`LolgpsError` if ``simulator`` cannot simulate ``plant``: MuJoCo's world
    simulates the arm as its URDF describes it, the plant variations are PyBullet's."""
    if simulator == "mujoco" and replace(plant, limits=NOMINAL_PLANT.limits) != NOMINAL_PLANT:
        raise LolgpsError(
            "--sim mujoco simulates the arm as its URDF describes it: the plant flags "
            "(--plant-inertia-scale, --payload, --gravity-compensation, --joint-friction, "
            "--obs-noise, --action-delay) need --sim pybullet"
        )
