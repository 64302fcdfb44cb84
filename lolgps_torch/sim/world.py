"""The peg-insertion world in PyBullet (DIRECT mode), the default engine of the simulator seam
(:class:`~lolgps_torch.sim.simulator.World` holds the dynamics common to every engine: the
torque ``clip(u + g(q), -effort, effort)`` held for ``substeps`` physics steps).

Only the peg collides with the table and the hole (collision filters).  The plant
(:class:`~lolgps_torch.sim.plant.PlantConfig`) may differ from the URDF: other link inertias,
a payload, another gravity compensation, joint friction, sensor noise and a command delay
(``u`` above is then the command issued ``d`` earlier).

The arm's visual shapes are not loaded unless pictures are taken (:class:`PegWorld`'s
``meshes``; ``URDF_IGNORE_VISUAL_SHAPES`` otherwise): PyBullet reads every visual mesh file
it is given (seconds for a description with 135 MB of meshes, docs/PERFORMANCE.md), and
nothing it simulates depends on visual shapes.

The hole is a static body of boxes (:func:`~lolgps_torch.sim.geometry.hole_boxes`), moved to
the condition's planar position.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.geometry import damping_inertias, hole_boxes
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig, reshaped_urdf
from lolgps_torch.sim.pybullet_quiet import pb, silenced
from lolgps_torch.sim.simulator import World, WorldConfig

__all__ = ["PegWorld", "WorldConfig"]


class PegWorld(World):
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
        super().__init__(arm, config, nominal_mouth, plant)
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
        self._q_all: list[float] = [0.0] * len(self.movable)
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
        try:  # PyBullet keeps the link states of a body of at most so many links
            pb.getLinkState(self.body, self.point_link_id, physicsClientId=c)
        except pb.error:
            raise LolgpsError(
                f"{self.arm.source_path}: PyBullet cannot read the link states of this body of "
                f"{len(links)} links (getLinkState failed): remove links the arm does not need "
                f"(another arm, sensors) from the URDF, or try --sim mujoco"
            ) from None
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
        zeros = [0.0] * len(self.movable)
        M = np.asarray(pb.calculateMassMatrix(body, zeros, physicsClientId=c))
        damping = [pb.getJointInfo(body, j, physicsClientId=c)[6] for j in self.joint_ids]
        m_eff, needs = damping_inertias(M, self.actuated_in_movable, damping, self.config)
        for j, m, need in zip(self.joint_ids, m_eff, needs, strict=True):
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

    def plant_urdf(self) -> str:
        """The URDF of the arm as simulated: each link's mass and inertia times its plant
        factor, the peg link's mass raised by the payload (:meth:`_reshape`)."""
        c = self.client
        names = [
            pb.getJointInfo(self.body, i, physicsClientId=c)[12].decode()
            for i in range(pb.getNumJoints(self.body, physicsClientId=c))
        ]
        factors = dict(zip(names, self.plant.link_factors(len(names)).tolist(), strict=True))
        return reshaped_urdf(self.arm.urdf_text, factors, {self.arm.peg_link: self.plant.payload})

    def _build_hole(self) -> int:
        """The hole's boxes (:func:`hole_boxes`) as one static body."""
        c = self.client
        extents, positions, orientations = [], [], []
        for box in hole_boxes(self.arm.peg_radius, self.config):
            pos, orn = box.centre, [0, 0, 0, 1]
            if box.yaw is not None:
                yaw = pb.getQuaternionFromEuler([0.0, 0.0, box.yaw])
                tilt = pb.getQuaternionFromEuler([0.0, box.tilt, 0.0])
                pos, orn = pb.multiplyTransforms([0, 0, 0], yaw, box.centre, tilt)
            extents.append(box.half_extents)
            positions.append(pos)
            orientations.append(orn)
        shape = pb.createCollisionShapeArray(
            [pb.GEOM_BOX] * len(extents),
            halfExtents=extents,
            collisionFramePositions=positions,
            collisionFrameOrientations=orientations,
            physicsClientId=c,
        )
        body = pb.createMultiBody(0.0, shape, -1, [0, 0, 0], physicsClientId=c)
        pb.changeDynamics(body, -1, lateralFriction=self.config.friction, physicsClientId=c)
        return int(body)

    def _move_hole(self, mouth: np.ndarray) -> None:
        pb.resetBasePositionAndOrientation(
            self.hole, mouth.tolist(), [0, 0, 0, 1], physicsClientId=self.client
        )

    def _point_pose(self) -> tuple[np.ndarray, np.ndarray]:
        state = pb.getLinkState(
            self.body,
            self.point_link_id,
            computeForwardKinematics=True,
            physicsClientId=self.client,
        )
        R = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        return np.asarray(state[4]), R

    def _set_joints(self, q: np.ndarray) -> None:
        for j, qj in zip(self.joint_ids, q, strict=True):
            pb.resetJointState(self.body, j, float(qj), 0.0, physicsClientId=self.client)

    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        states = pb.getJointStates(self.body, self.movable, physicsClientId=self.client)
        self._q_all = [s[0] for s in states]
        q = np.array([states[i][0] for i in self.actuated_in_movable])
        qd = np.array([states[i][1] for i in self.actuated_in_movable])
        return q, qd

    def _physics_step(self, tau: np.ndarray) -> None:
        c = self.client
        pb.setJointMotorControlArray(
            self.body, self.joint_ids, pb.TORQUE_CONTROL, forces=tau.tolist(), physicsClientId=c
        )
        pb.stepSimulation(physicsClientId=c)

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

    def effective_inertia(self, q: Sequence[float]) -> Tensor:
        client, body = self.reference
        q_all = [0.0] * len(self.movable)
        for j, i in zip(self.actuated_in_movable, range(self.arm.dof), strict=True):
            q_all[j] = q[i]
        M = torch.tensor(pb.calculateMassMatrix(body, q_all, physicsClientId=client))
        idx = torch.tensor(self.actuated_in_movable)
        Minv = torch.linalg.inv(M)[idx][:, idx]
        return (1.0 / torch.diagonal(Minv)).to(dtype=torch.float64)

    def joint_damping(self) -> Tensor:
        client, body = self.reference
        b = [pb.getJointInfo(body, j, physicsClientId=client)[6] for j in self.joint_ids]
        return torch.tensor(b, dtype=torch.float64)

    def close(self) -> None:
        for client in {self.client, self.reference[0]}:
            if pb.isConnected(client):
                pb.disconnect(client)
