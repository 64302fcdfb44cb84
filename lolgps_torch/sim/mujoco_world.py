"""The peg-insertion world in MuJoCo (``--sim mujoco``), the second engine of the simulator seam
(:class:`~lolgps_torch.sim.simulator.World` holds the dynamics common to every engine: the
torque ``clip(u + g(q), -effort, effort)`` held for ``substeps`` physics steps).

The arm's URDF goes through MuJoCo's own URDF compiler (:func:`mujoco_urdf`): visual shapes
are dropped (PyBullet's world drops them too), and so are the collision shapes of every link
but the peg's, since only the peg touches the world; every link stays a body of its own, so
the peg and point frames keep their names.  Everything else is made to match PyBullet's world:

- the same table and funnel boxes (:func:`~lolgps_torch.sim.simulator.hole_boxes`) on a mocap
  body moved to the condition's position;
- friction: PyBullet multiplies the hole's coefficient (``--friction``) by the peg link's own
  (0.5 unless its URDF says otherwise), MuJoCo takes the larger of the two geoms'; both get
  the product here;
- the same physics step ``dt / substeps`` and gravity; the gravity compensation is MuJoCo's
  inverse dynamics at zero velocity (``mj_rne``) at the start of each control step;
- the URDF's joint damping is applied explicitly at the velocity before each physics step, as
  PyBullet does (MuJoCo's own damping, integrated implicitly, is switched off), and so is
  Bullet's link damping (:meth:`ArmDynamics.link_damping
  <lolgps_torch.robot.rigid_body.ArmDynamics.link_damping>`), as external wrenches; the same
  rotor-like inertia is added where joint damping would be unstable, so that the arm's model
  (:class:`~lolgps_torch.sim.model.ControlStep`) is the same for both engines.

What stays different: MuJoCo's contacts are soft (the peg may sink a fraction of a
millimetre into a plate) and its joint limits are soft constraints; a link whose inertia breaks the triangle inequality is balanced by MuJoCo's
compiler where PyBullet zeroes it.  Only the nominal plant is simulated
(:func:`~lolgps_torch.sim.simulator.check_plant`).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence

import mujoco
import numpy as np
import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.simulator import (
    World,
    WorldConfig,
    check_plant,
    damping_inertias,
    hole_boxes,
)

PYBULLET_LINK_FRICTION = 0.5  # a URDF link's lateral friction in PyBullet unless it sets one
LINK_DAMPING = 0.04  # btMultiBody's linear and angular link damping (sim/model.py)
HOLE = "lolgps_hole"


def mujoco_urdf(arm: ArmSpec) -> tuple[str, float]:
    """The arm's URDF as MuJoCo's compiler is given it (module docstring), and the peg link's
    lateral friction as PyBullet reads it (``<contact><lateral_friction>``, else 0.5)."""
    root = ET.fromstring(arm.urdf_text)
    friction = PYBULLET_LINK_FRICTION
    for link in root.iter("link"):
        for visual in link.findall("visual"):
            link.remove(visual)
        if link.get("name") == arm.peg_link:
            lateral = link.find("contact/lateral_friction")
            if lateral is not None:
                friction = float(lateral.get("value", friction))
        else:
            for collision in link.findall("collision"):
                link.remove(collision)
    for old in root.findall("mujoco"):
        root.remove(old)
    extension = ET.SubElement(root, "mujoco")
    ET.SubElement(extension, "compiler", fusestatic="false", balanceinertia="true")
    return ET.tostring(root, encoding="unicode"), friction


def _quaternion(yaw: float, tilt: float) -> np.ndarray:
    """``Rz(yaw) Ry(tilt)`` as a unit quaternion ``(w, x, y, z)``."""
    cy, sy, ct, st = np.cos(yaw / 2), np.sin(yaw / 2), np.cos(tilt / 2), np.sin(tilt / 2)
    return np.array([cy * ct, -sy * st, cy * st, sy * ct])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of ``[n, 3]`` arrays (np.cross costs more on a few rows)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


class MujocoWorld(World):
    """One MuJoCo model and its data with the arm, the table and the hole (module docstring).
    Not picklable: build it in the process that uses it.

    :param arm: the arm. :param config: simulation and hole geometry.
    :param nominal_mouth: the hole's mouth at offset zero (world, m).
    :param plant: how the simulated arm departs from its URDF (the nominal plant only).
    """

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        plant: PlantConfig = NOMINAL_PLANT,
    ) -> None:
        check_plant("mujoco", plant)
        super().__init__(arm, config, nominal_mouth, plant)
        self.model = self._compile()
        m = self.model
        self.data = mujoco.MjData(m)
        self._rest = mujoco.MjData(m)  # inverse dynamics at rest, mass matrices
        joints = [m.joint(name).id for name in arm.joint_names]
        self.qpos_ids = m.jnt_qposadr[joints]
        self.dof_ids = m.jnt_dofadr[joints]
        self.point_body = m.body(arm.point_link).id
        self.hole_mocap = m.body_mocapid[m.body(HOLE).id]
        self.damped = np.array(
            [b for b in range(1, m.nbody) if m.body_mass[b] > 0 and m.body_mocapid[b] < 0]
        )
        self._stabilise_damping(joints)
        # the URDF's joint damping, applied explicitly as PyBullet does (MuJoCo's own is
        # implicit, which damps the light wrist joints far less within a physics step)
        self.damping = m.dof_damping[self.dof_ids].copy()
        m.dof_damping[:] = 0.0
        # no Coulomb friction: the nominal plant has none (PyBullet's world overrides a URDF's
        # <dynamics friction> with --joint-friction, 0), MuJoCo's compiler would keep it
        m.dof_frictionloss[:] = 0.0
        self.set_hole((0.0, 0.0))

    def _compile(self) -> mujoco.MjModel:
        """The arm (:func:`mujoco_urdf`), the hole's mocap body and the physics settings."""
        cfg = self.config
        text, peg_friction = mujoco_urdf(self.arm)
        friction = [cfg.friction * peg_friction, 0.005, 0.0001]  # sliding; MuJoCo's others
        try:
            spec = mujoco.MjSpec.from_string(text)
            spec.option.timestep = cfg.dt / cfg.substeps
            spec.option.gravity = [0.0, 0.0, -cfg.gravity]
            spec.option.enableflags |= int(mujoco.mjtEnableBit.mjENBL_MULTICCD)
            for geom in spec.geoms:
                geom.friction = friction
            hole = spec.worldbody.add_body(name=HOLE, mocap=True)
            for box in hole_boxes(self.arm.peg_radius, cfg):
                yaw = box.yaw or 0.0
                turn = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0],
                                 [0.0, 0.0, 1.0]])  # fmt: skip
                hole.add_geom(
                    type=mujoco.mjtGeom.mjGEOM_BOX,
                    size=box.half_extents,
                    pos=turn @ np.asarray(box.centre),
                    quat=_quaternion(yaw, box.tilt),
                    friction=friction,
                )
            return spec.compile()
        except ValueError as error:
            message = str(error).strip().splitlines()[0] if str(error).strip() else repr(error)
            raise LolgpsError(f"MuJoCo could not load {self.arm.source_path}: {message}") from None

    def _stabilise_damping(self, joints: list[int]) -> None:
        """Raise the principal inertias of a joint's child body where PyBullet's world does
        (:func:`~lolgps_torch.sim.simulator.damping_inertias`), so that both engines simulate
        the arm the model describes."""
        m = self.model
        M = self._mass_matrix(np.zeros(self.arm.dof))
        damping = m.dof_damping[self.dof_ids].tolist()
        m_eff, needs = damping_inertias(M, range(self.arm.dof), damping, self.config)
        for j, m_j, need in zip(joints, m_eff, needs, strict=True):
            if m_j < need:
                body = m.jnt_bodyid[j]
                m.body_inertia[body] = m.body_inertia[body] + need - m_j

    def _mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """The actuated joints' mass matrix ``[dof, dof]`` at joint angles ``q``."""
        m, rest = self.model, self._rest
        rest.qpos[self.qpos_ids] = q
        mujoco.mj_fwdPosition(m, rest)
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, full, rest.qM)
        return full[np.ix_(self.dof_ids, self.dof_ids)]

    def _move_hole(self, mouth: np.ndarray) -> None:
        self.data.mocap_pos[self.hole_mocap] = mouth

    def _set_joints(self, q: np.ndarray) -> None:
        m, d = self.model, self.data
        mouth = d.mocap_pos.copy()
        mujoco.mj_resetData(m, d)  # no warm start or contact carried over from a rollout
        d.mocap_pos[:] = mouth
        d.qpos[self.qpos_ids] = q
        mujoco.mj_forward(m, d)

    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self.data.qpos[self.qpos_ids].copy(), self.data.qvel[self.dof_ids].copy()

    def _point_pose(self) -> tuple[np.ndarray, np.ndarray]:
        mujoco.mj_kinematics(self.model, self.data)
        body = self.point_body
        return self.data.xpos[body].copy(), self.data.xmat[body].reshape(3, 3).copy()

    def _physics_step(self, tau: np.ndarray) -> None:
        m, d = self.model, self.data
        mujoco.mj_step1(m, d)  # positions and velocities: what the damping wrenches need
        d.xfrc_applied[self.damped] = self._link_damping()
        d.qfrc_applied[self.dof_ids] = tau - self.damping * d.qvel[self.dof_ids]
        mujoco.mj_step2(m, d)
        if d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0:
            raise NumericalError("the simulation blew up: MuJoCo's accelerations are not finite")

    def _link_damping(self) -> np.ndarray:
        """Bullet's link damping as wrenches ``[bodies, 6]`` (force, then moment) at the
        centres of mass of the bodies :attr:`damped`: on a body of mass m, COM velocity v,
        angular velocity w and world inertia I, ``-k (1 + |v|) m v`` and
        ``-k (1 + |w|) I w`` (k = :data:`LINK_DAMPING`)."""
        m, d, b = self.model, self.data, self.damped
        omega, linear = d.cvel[b, :3], d.cvel[b, 3:]  # at the subtree's centre of mass
        v = linear + _cross(omega, d.xipos[b] - d.subtree_com[m.body_rootid[b]])
        R = d.ximat[b].reshape(-1, 3, 3)
        local = m.body_inertia[b] * np.einsum("bji,bj->bi", R, omega)
        I_omega = np.einsum("bij,bj->bi", R, local)
        speed = np.sqrt(np.einsum("bi,bi->b", v, v))[:, None]
        spin = np.sqrt(np.einsum("bi,bi->b", omega, omega))[:, None]
        force = -LINK_DAMPING * (1 + speed) * m.body_mass[b, None] * v
        moment = -LINK_DAMPING * (1 + spin) * I_omega
        return np.concatenate([force, moment], axis=1)

    def gravity_compensation(self) -> np.ndarray:
        """``g(q) [dof]`` at the current joint angles: MuJoCo's inverse dynamics at rest."""
        m, rest = self.model, self._rest
        rest.qpos[:] = self.data.qpos
        mujoco.mj_kinematics(m, rest)
        mujoco.mj_comPos(m, rest)
        mujoco.mj_comVel(m, rest)  # zero: rest.qvel stays zero
        out = np.zeros(m.nv)
        mujoco.mj_rne(m, rest, 0, out)
        return out[self.dof_ids]

    def effective_inertia(self, q: Sequence[float]) -> Tensor:
        M = self._mass_matrix(np.asarray(q, dtype=np.float64))
        return torch.from_numpy(1.0 / np.diag(np.linalg.inv(M)))

    def joint_damping(self) -> Tensor:
        return torch.from_numpy(self.damping.copy())

    def close(self) -> None:
        """Nothing to release: the model and data are freed with the world."""
