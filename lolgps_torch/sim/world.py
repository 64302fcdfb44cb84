"""The peg-insertion world in PyBullet (DIRECT mode).

Dynamics: each control step of ``dt`` holds the command for ``substeps`` physics steps.  The
joint torque sent at every physics step is ``clip(u + g(q), -effort, effort)``, where ``g(q)``
is the gravity-compensation torque (inverse dynamics at zero velocity and acceleration)
evaluated at the start of the control step, as a torque-controlled arm's own gravity
compensation would.  Only the peg collides with the table and the hole.  The plant
(:class:`~lolgps_torch.sim.plant.PlantConfig`) may differ from the URDF: other link inertias,
a payload, another gravity compensation, joint friction, sensor noise and a command delay
(``u`` above is then the command issued ``d`` earlier).

The arm's visual shapes are not loaded unless pictures are taken (:class:`PegWorld`'s
``meshes``; ``URDF_IGNORE_VISUAL_SHAPES`` otherwise): PyBullet reads every visual mesh file
it is given (seconds for a description with 135 MB of meshes, docs/PERFORMANCE.md), and
nothing it simulates depends on visual shapes.

The hole is a square funnel cut in a table: four guide plates tilted so the clearance per side
narrows from ``clearance_mouth`` at the table surface to ``clearance_bottom`` at the floor,
``depth`` below.  The condition is the hole's planar position.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass

import numpy as np

from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.plant import (
    NOMINAL_PLANT,
    VELOCITY_NOISE_RATIO,
    PlantConfig,
    physics_steps,
)
from lolgps_torch.sim.pybullet_quiet import pb, silenced
from lolgps_torch.state import StateLayout


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
    :param known_delay: the command delay (s) the learner allows for, whole physics steps: the
        state carries the actions of the last ceil(d / dt) control steps and the arm's model
        acts on each command d late (set it to the arm's latency)
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
        physics_steps(self.known_delay, self.dt / self.substeps, "--known-delay")

    @property
    def delay_steps(self) -> int:
        """The known delay in physics steps."""
        return physics_steps(self.known_delay, self.dt / self.substeps, "--known-delay")

    @property
    def history(self) -> int:
        """Actions kept in the state: ``ceil(d / dt)`` for the known delay d."""
        return -(-self.delay_steps // self.substeps)

    def layout(self, dof: int) -> StateLayout:
        """The state vector's layout for an arm of ``dof`` actuated joints."""
        return StateLayout(dof, self.history)


class PegWorld:
    """One PyBullet client with the arm, the table and the hole.  Not picklable: build it in
    the process that uses it.

    :param arm: the arm. :param config: simulation and hole geometry.
    :param nominal_mouth: the hole's mouth at offset zero (world, m).
    :param meshes: load the arm's visual shapes, meshes included (only pictures need them).
    :param plant: how the simulated arm departs from its URDF.
    """

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        meshes: bool = False,
        plant: PlantConfig = NOMINAL_PLANT,
    ) -> None:
        self.arm, self.config, self.plant = arm, config, plant
        self.layout = config.layout(arm.dof)
        self.nominal_mouth = np.asarray(nominal_mouth, dtype=np.float64)
        self.delay = plant.delay_steps(config.dt / config.substeps)
        self.client = self._connect()
        self.body = self._load(self.client, meshes)
        self._index_joints()
        # the arm as its URDF describes it: the simulated body itself unless the plant differs
        self.reference = (self.client, self.body)
        if plant.reshaped:
            reference = self._connect()
            self.reference = (reference, self._load(reference, False))
            self._stabilise_damping(*self.reference)
            # before PyBullet's first mass matrix or inverse dynamics of the body, which
            # builds a copy of its masses that later changes do not reach
            self._reshape()
        self._stabilise_damping(self.client, self.body)
        self.hole = self._build_hole()
        self.offsets = np.asarray(arm.point_offsets, dtype=np.float64)  # [2, 3]
        self.effort = np.asarray(arm.effort, dtype=np.float64)
        self.targets = np.zeros((2, 3))
        self._prev_points = np.zeros(6)
        self._points = np.zeros(6)
        self._q_all: list[float] = [0.0] * len(self.movable)
        self._queue = np.zeros((self.delay, arm.dof))  # commands issued, not yet acting
        self._issued = np.zeros((config.history, arm.dof))  # the last commands, newest first
        self._noise: np.random.Generator | None = None
        self.set_hole((0.0, 0.0))

    def _connect(self) -> int:
        """A new PyBullet client with the world's physics step and gravity."""
        c = int(pb.connect(pb.DIRECT))
        pb.setPhysicsEngineParameter(
            fixedTimeStep=self.config.dt / self.config.substeps,
            deterministicOverlappingPairs=1,
            physicsClientId=c,
        )
        pb.setGravity(0, 0, -self.config.gravity, physicsClientId=c)
        return c

    def _load(self, client: int, meshes: bool) -> int:
        """The arm's URDF as a fixed-base body of ``client``."""
        arm = self.arm
        with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as fh:
            fh.write(arm.urdf_text)
        try:
            flags = pb.URDF_USE_INERTIA_FROM_FILE | (0 if meshes else pb.URDF_IGNORE_VISUAL_SHAPES)
            with silenced():  # PyBullet's own warnings; the loader has said what matters
                body = pb.loadURDF(fh.name, useFixedBase=True, flags=flags, physicsClientId=client)
        except pb.error as exc:
            raise LolgpsError(f"PyBullet could not load {arm.source_path}: {exc}") from None
        finally:
            os.unlink(fh.name)
        return int(body)

    def _index_joints(self) -> None:
        c = self.client
        names, links, movable = {}, {}, []
        for i in range(pb.getNumJoints(self.body, physicsClientId=c)):
            info = pb.getJointInfo(self.body, i, physicsClientId=c)
            names[info[1].decode()] = i
            links[info[12].decode()] = i
            if info[2] != pb.JOINT_FIXED:
                movable.append(i)
        self.joint_ids = [names[n] for n in self.arm.joint_names]
        self.point_link_id = links[self.arm.point_link]
        self.peg_link_id = links[self.arm.peg_link]
        self.movable = movable  # every non-fixed joint, the order inverse dynamics expects
        self.actuated_in_movable = [movable.index(j) for j in self.joint_ids]
        # the velocity motors, at target speed zero, are the joints' Coulomb friction
        pb.setJointMotorControlArray(
            self.body,
            self.joint_ids,
            pb.VELOCITY_CONTROL,
            forces=[self.plant.joint_friction] * len(self.joint_ids),
            physicsClientId=c,
        )
        for link in [-1, *links.values()]:
            if link != self.peg_link_id:
                pb.setCollisionFilterGroupMask(self.body, link, 0, 0, physicsClientId=c)

    def _stabilise_damping(self, c: int, body: int) -> None:
        """Add rotor-like inertia where a joint's damping would be unstable (to ``body`` of
        client ``c``).

        PyBullet applies joint damping b explicitly, which is stable only while
        b dt / m < ~2, with m the joint's effective inertia 1 / (M^-1)_jj. Where
        m < damping_margin b dt, the child link's principal inertias are raised by the
        difference (as a motor's reflected rotor inertia would); other arms are untouched.
        """
        dt = self.config.dt / self.config.substeps
        zeros = [0.0] * len(self.movable)
        M = np.asarray(pb.calculateMassMatrix(body, zeros, physicsClientId=c))
        m_eff = 1.0 / np.diag(np.linalg.inv(M))[self.actuated_in_movable]
        for j, m in zip(self.joint_ids, m_eff, strict=True):
            need = self.config.damping_margin * pb.getJointInfo(body, j, physicsClientId=c)[6] * dt
            if m < need:  # the child link of joint j has index j
                inertia = pb.getDynamicsInfo(body, j, physicsClientId=c)[2]
                raised = [v + need - m for v in inertia]
                pb.changeDynamics(body, j, localInertiaDiagonal=raised, physicsClientId=c)

    def _reshape(self) -> None:
        """The plant's link masses and inertias: link i's scaled by its factor, the peg link's
        mass raised by the payload (at its centre of mass)."""
        c = self.client
        factors = self.plant.link_factors(pb.getNumJoints(self.body, physicsClientId=c))
        for link, f in enumerate(factors.tolist()):
            mass, _, inertia = pb.getDynamicsInfo(self.body, link, physicsClientId=c)[:3]
            mass = mass * f + (self.plant.payload if link == self.peg_link_id else 0.0)
            pb.changeDynamics(
                self.body,
                link,
                mass=mass,
                localInertiaDiagonal=[v * f for v in inertia],
                physicsClientId=c,
            )

    def _build_hole(self) -> int:
        """Table slab with a square opening, four tilted guide plates and a floor (static)."""
        cfg, c = self.config, self.client
        a_top = self.arm.peg_radius + cfg.clearance_mouth
        a_bot = self.arm.peg_radius + cfg.clearance_bottom
        h, D, W = cfg.plate_thickness / 2, cfg.depth, cfg.table_half_size
        norm = math.hypot(D, a_bot - a_top)
        nx, nz = D / norm, (a_bot - a_top) / norm  # outward normal of the +x plate's face
        face_mid = np.array([(a_top + a_bot) / 2, 0.0, -D / 2])
        centre = face_mid + h * np.array([nx, 0.0, nz])
        tilt = pb.getQuaternionFromEuler([0.0, math.atan2(-nz, nx), 0.0])
        half_plate = [h, a_top + 2 * h, norm / 2]
        extents, positions, orientations = [], [], []
        for k in range(4):
            yaw = pb.getQuaternionFromEuler([0.0, 0.0, k * math.pi / 2])
            pos, orn = pb.multiplyTransforms([0, 0, 0], yaw, centre.tolist(), tilt)
            extents.append(half_plate)
            positions.append(pos)
            orientations.append(orn)
        outer = a_top + 2 * h  # the slab leaves a square opening of this half-width
        zc, zh = -(D + 2 * h) / 2, (D + 2 * h) / 2
        for k in range(4):  # a pinwheel of four slabs around the opening
            yaw = pb.getQuaternionFromEuler([0.0, 0.0, k * math.pi / 2])
            pos, orn = pb.multiplyTransforms(
                [0, 0, 0], yaw, [(outer + W) / 2, (W - outer) / 2, zc], [0, 0, 0, 1]
            )
            extents.append([(W - outer) / 2, (W + outer) / 2, zh])
            positions.append(pos)
            orientations.append(orn)
        extents.append([outer, outer, h])
        positions.append([0.0, 0.0, -D - h])
        orientations.append([0, 0, 0, 1])
        shape = pb.createCollisionShapeArray(
            [pb.GEOM_BOX] * len(extents),
            halfExtents=extents,
            collisionFramePositions=positions,
            collisionFrameOrientations=orientations,
            physicsClientId=c,
        )
        body = pb.createMultiBody(0.0, shape, -1, [0, 0, 0], physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=cfg.friction, physicsClientId=c)
        return int(body)

    def set_hole(self, offset: tuple[float, float]) -> None:
        """Move the hole to ``nominal + (dx, dy)``; targets: tip at the floor centre, top above."""
        mouth = self.nominal_mouth + np.array([offset[0], offset[1], 0.0])
        pb.resetBasePositionAndOrientation(
            self.hole, mouth.tolist(), [0, 0, 0, 1], physicsClientId=self.client
        )
        tip = mouth - np.array([0.0, 0.0, self.config.depth])
        self.targets = np.stack([tip, tip - self.offsets[1]])  # top offset points down the axis

    def points(self) -> np.ndarray:
        """World positions of the tip and top points, ``[2, 3]``."""
        state = pb.getLinkState(
            self.body,
            self.point_link_id,
            computeForwardKinematics=True,
            physicsClientId=self.client,
        )
        R = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        return np.asarray(state[4]) + self.offsets @ R.T

    def reset(self, q0: np.ndarray, key: tuple[int, ...] = (0,)) -> np.ndarray:
        """Put the arm at rest at ``q0``, with no command pending, and return the state; the
        rollout's sensor noise is drawn from ``key`` (:meth:`PlantConfig.noise`)."""
        for j, qj in zip(self.joint_ids, q0, strict=True):
            pb.resetJointState(self.body, j, float(qj), 0.0, physicsClientId=self.client)
        self._queue = np.zeros_like(self._queue)
        self._issued = np.zeros_like(self._issued)
        self._noise = self.plant.noise(key)
        self._prev_points = (self.points() - self.targets).reshape(6)
        return self.observe()  # zero point velocity at rest

    def observe(self) -> np.ndarray:
        """The state vector ``[dX]`` (see :class:`StateLayout`)."""
        c = self.client
        states = pb.getJointStates(self.body, self.movable, physicsClientId=c)
        self._q_all = [s[0] for s in states]
        q = np.array([states[i][0] for i in self.actuated_in_movable])
        qd = np.array([states[i][1] for i in self.actuated_in_movable])
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
        return np.concatenate([q, qd, pts, vel, self._issued.reshape(-1)])

    def step(self, u: np.ndarray) -> np.ndarray:
        """Issue torque ``u`` (on top of gravity compensation) for one control step, starting
        from the state the last :meth:`reset`, :meth:`observe` or :meth:`step` returned; with a
        delay of d physics steps, the commands issued d steps earlier act instead."""
        c, substeps = self.client, self.config.substeps
        if not np.all(np.isfinite(u)):
            raise NumericalError("non-finite action: the controller produced NaN or inf torques")
        g = self.gravity_compensation()
        held = np.concatenate([self._queue, np.broadcast_to(u, (substeps, len(u)))])
        self._queue = held[substeps:]
        # the commands as they act (within the effort limits): past commands beyond them
        # would grow without bound under a controller that feeds them back
        acting = np.clip(u + g, -self.effort, self.effort) - g
        self._issued = np.concatenate([acting[None], self._issued])[: len(self._issued)]
        self._prev_points = self._points
        for s in range(substeps):
            tau = np.clip(held[s] + g, -self.effort, self.effort).tolist()
            pb.setJointMotorControlArray(
                self.body, self.joint_ids, pb.TORQUE_CONTROL, forces=tau, physicsClientId=c
            )
            pb.stepSimulation(physicsClientId=c)
        return self.observe()

    def gravity_compensation(self) -> np.ndarray:
        """``g(q) [dof]`` at the current joint angles, as the plant computes it: inverse
        dynamics at rest of the simulated body (``plant``), of the URDF (``model``), or 0."""
        if self.plant.gravity_compensation == "none":
            return np.zeros(self.arm.dof)
        client, body = (self.client, self.body)
        if self.plant.gravity_compensation == "model":
            client, body = self.reference
        zeros = [0.0] * len(self.movable)
        g = pb.calculateInverseDynamics(body, self._q_all, zeros, zeros, physicsClientId=client)
        return np.asarray(g)[self.actuated_in_movable]

    def tip_distance(self) -> float:
        """Distance (m) from the peg tip to the hole-floor target."""
        return float(np.linalg.norm(self.points()[0] - self.targets[0]))

    def close(self) -> None:
        for client in {self.client, self.reference[0]}:
            if pb.isConnected(client):
                pb.disconnect(client)
