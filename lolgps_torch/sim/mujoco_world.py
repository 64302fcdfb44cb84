"""The peg-insertion world in MuJoCo (``--sim mujoco``), the second engine of the simulator seam
(:class:`~lolgps_torch.sim.simulator.World` holds the dynamics common to every engine: the
torque ``clip(u + g(q), -effort, effort)`` held for ``substeps`` physics steps).

The arm's URDF goes through MuJoCo's own URDF compiler (:func:`mujoco_urdf`): visual shapes
are dropped (PyBullet's world drops them too), and so are the collision shapes of every link
but the peg's, since only the peg touches the world; every link stays a body of its own, so
the peg and point frames keep their names.  Everything else is made to match PyBullet's world:

- the same table and funnel boxes (:func:`~lolgps_torch.sim.geometry.hole_boxes`) on a mocap
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

What stays different: contact.  MuJoCo's contacts are soft, here with a time constant of
:data:`CONTACT_TIME_CONSTANT` physics steps, and a physics step with the peg touching is
taken as :data:`CONTACT_REFINE` finer ones (:func:`_physics_steps`); the peg sinks 2–3 mm
into a plate under the controllers' pushes, and up to 11 mm into the table when pushed down by
30 N before it rests.  Its joint limits are soft constraints; a link whose inertia breaks the triangle inequality is balanced by MuJoCo's
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
from lolgps_torch.sim.geometry import damping_inertias, hole_boxes
from lolgps_torch.sim.mujoco_compat import mass_matrix, same_contact
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.simulator import World, WorldConfig, check_plant

PYBULLET_LINK_FRICTION = 0.5  # a URDF link's lateral friction in PyBullet unless it sets one
LINK_DAMPING = 0.04  # btMultiBody's linear and angular link damping (sim/model.py)
HOLE = "lolgps_hole"
# Contacts (docs/RESULTS.md, MuJoCo): the peg touching the table or the hole makes a physics
# step this many finer ones, and contacts take this many physics steps as their time constant
# (MuJoCo's default, 0.02 s, is its floor of two)
CONTACT_REFINE = 2
CONTACT_TIME_CONSTANT = 4


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


CROSS = ([1, 2, 0], [2, 0, 1])  # a x b = a[CROSS[0]] b[CROSS[1]] - a[CROSS[1]] b[CROSS[0]]


def link_damping(
    cvel: np.ndarray, com: np.ndarray, root_com: np.ndarray, R: np.ndarray,
    mass: np.ndarray, inertia: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """Bullet's link damping as wrenches ``[..., B, 2, 3]`` (force, then moment) at B bodies'
    centres of mass: on a body of mass m, COM velocity v, angular velocity w and world inertia
    I, ``-k (1 + |v|) m v`` and ``-k (1 + |w|) I w`` (k = :data:`LINK_DAMPING`).

    :param cvel: MuJoCo's ``cvel`` rows ``[..., B, 6]``: w, then the linear velocity of the
        point at the root's subtree COM ``root_com [..., 1, 3]``. :param com: the COMs
        ``[..., B, 3]``. :param R: the inertia frames ``[..., B, 3, 3]``. :param mass:
        ``-k m [B, 1]``. :param inertia: ``-k`` times the principal inertias ``[B, 3]``.

    Elementwise products and sums written out term by term, no matrix product or reduction:
    each body's wrench has the same bits whatever the leading axes hold (a batch of worlds
    stepped together, or one world).
    """
    omega = cvel[..., :3]
    lever = com - root_com
    a, b = CROSS
    moving = np.empty((*cvel.shape[:-1], 2, 3))  # v, then w
    moving[..., 0, :] = cvel[..., 3:] + (
        omega[..., a] * lever[..., b] - omega[..., b] * lever[..., a]
    )
    moving[..., 1, :] = omega
    square = np.square(moving)
    factor = 1.0 + np.sqrt(square[..., 0] + square[..., 1] + square[..., 2])  # [..., B, 2]
    turned = R * omega[..., :, None]
    body_omega = inertia * (turned[..., 0, :] + turned[..., 1, :] + turned[..., 2, :])
    turned = R * body_omega[..., None, :]  # then -k R I_body R^T w
    moving[..., 1, :] = turned[..., 0] + turned[..., 1] + turned[..., 2]
    factor[..., 0] *= mass[:, 0]
    return factor[..., None] * moving


def _index(ids: np.ndarray) -> slice | np.ndarray:
    """``ids`` as a slice where they are consecutive (a view, not a copy, when indexing)."""
    if len(ids) and np.array_equal(ids, np.arange(ids[0], ids[0] + len(ids))):
        return slice(int(ids[0]), int(ids[0]) + len(ids))
    return ids


class MujocoWorld(World):
    """One MuJoCo model and its data with the arm, the table and the hole (module docstring).
    Not picklable: build it in the process that uses it.

    :param arm: the arm. :param config: simulation and hole geometry.
    :param nominal_mouth: the hole's mouth at offset zero (world, m).
    :param plant: how the simulated arm departs from its URDF (the nominal plant only).
    """

    lockstep = True  # Python, not MuJoCo, costs most of a physics step (docs/PERFORMANCE.md)

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        plant: PlantConfig = NOMINAL_PLANT,
    ) -> None:
        check_plant("mujoco", plant)
        super().__init__(arm, config, nominal_mouth, plant)
        self.physics_step = config.dt / config.substeps
        self.model = self._compile()
        m = self.model
        self.data = mujoco.MjData(m)
        self._rest = mujoco.MjData(m)  # inverse dynamics at rest, mass matrices
        joints = [m.joint(name).id for name in arm.joint_names]
        self.qpos_ids = m.jnt_qposadr[joints]
        self.dof_ids = m.jnt_dofadr[joints]
        self._q, self._dofs = _index(self.qpos_ids), _index(self.dof_ids)
        self.point_body = m.body(arm.point_link).id
        self.hole_mocap = m.body_mocapid[m.body(HOLE).id]
        self._stabilise_damping(joints)
        self._damping_views()
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
            spec.option.timestep = self.physics_step
            spec.option.gravity = [0.0, 0.0, -cfg.gravity]
            soft = [CONTACT_TIME_CONSTANT * self.physics_step, 1.0]  # time constant, damping ratio
            for geom in spec.geoms:
                geom.friction = friction
                geom.solref = soft
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
                    solref=soft,
                )
            same_contact(spec)
            return spec.compile()
        except ValueError as error:
            message = str(error).strip().splitlines()[0] if str(error).strip() else repr(error)
            raise LolgpsError(f"MuJoCo could not load {self.arm.source_path}: {message}") from None

    def _stabilise_damping(self, joints: list[int]) -> None:
        """Raise the principal inertias of a joint's child body where PyBullet's world does
        (:func:`~lolgps_torch.sim.geometry.damping_inertias`), so that both engines simulate
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
        return mass_matrix(m, rest)[np.ix_(self.dof_ids, self.dof_ids)]

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
        """The joints now; a physics step since the last reset whose accelerations were not
        finite (MuJoCo counts it, and resets the data) is a :class:`NumericalError`."""
        if self._badqacc.number > 0:
            raise NumericalError("the simulation blew up: MuJoCo's accelerations are not finite")
        return self._qpos[self._q].copy(), self._qvel[self._dofs].copy()

    def _point_pose(self) -> tuple[np.ndarray, np.ndarray]:
        mujoco.mj_kinematics(self.model, self.data)
        body = self.point_body
        return self.data.xpos[body].copy(), self.data.xmat[body].reshape(3, 3).copy()

    def _physics_step(self, tau: np.ndarray) -> None:
        _physics_steps([self], tau[None])

    @classmethod
    def step_together(cls, worlds: Sequence[World], u: np.ndarray) -> np.ndarray:
        """:meth:`step` of each world, their physics steps taken together: the link damping of
        all worlds in one pass of numpy (:func:`link_damping`), each world's numbers its own."""
        mine = [world for world in worlds if isinstance(world, MujocoWorld)]
        if len(mine) != len(worlds):
            raise TypeError("MujocoWorld.step_together steps MuJoCo worlds only")
        commands = [world._command(row) for world, row in zip(mine, u, strict=True)]
        moving = [i for i, world in enumerate(mine) if world.fault is None]  # not braked
        substeps = mine[0].config.substeps
        taus = np.array([commands[i] for i in moving]).reshape(-1, substeps, u.shape[1])
        for s in range(substeps):
            if not moving:
                break
            _physics_steps([mine[i] for i in moving], taus[:, s])
            still = [k for k, i in enumerate(moving) if not mine[i].check_limits()]
            moving, taus = [moving[k] for k in still], taus[still]
        for world in mine:
            world._steps += 1
        return np.stack([world.observe() for world in mine])

    def _damping_views(self) -> None:
        """Views into the data's arrays that :func:`_physics_steps` reads and writes, for the
        arm's bodies (1 up to the hole's; a massless one gets no wrench): these are the same
        arrays for the world's life, so each physics step costs no look-up of them."""
        m, d = self.model, self.data
        arm = slice(1, m.body(HOLE).id)
        (root,) = set(m.body_rootid[arm].tolist())  # a URDF is one tree
        self._mass = -LINK_DAMPING * m.body_mass[arm, None]
        self._inertia = -LINK_DAMPING * m.body_inertia[arm]  # principal, with rotors
        self._cvel, self._com = d.cvel[arm], d.xipos[arm]
        self._root_com = d.subtree_com[root : root + 1]
        self._R = d.ximat[arm].reshape(-1, 3, 3)
        self._wrench = d.xfrc_applied[arm].reshape(-1, 2, 3)
        self._qvel, self._qfrc = d.qvel, d.qfrc_applied
        self._qpos = d.qpos
        self._badqacc = d.warning[mujoco.mjtWarning.mjWARN_BADQACC]

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


def _physics_steps(worlds: Sequence[MujocoWorld], tau: np.ndarray) -> None:
    """One physics step ``h = dt / substeps`` of each of ``worlds`` (of one arm and
    configuration) with its row of joint torques ``tau: [n, dof]``, in MuJoCo's two halves
    (:func:`_second_half`).

    A world whose peg touches the table or the hole as the step starts takes it as
    :data:`CONTACT_REFINE` steps of ``h / CONTACT_REFINE`` with the same torques. At ``h``
    and MuJoCo's stiffest contacts (time constant 2 h), the peg's rim held on a plate's edge
    at the mouth let an exploring controller's feedback grow until the joints passed 70 rad/s
    or the simulation blew up (6 of 160 batches of the KUKA's seed-2 first controllers), where
    PyBullet's arm stays below 9 rad/s; with the contacts' time constant at 4 h and the step
    halved in contact, none of them did (``scripts/research/first_controller.py``,
    docs/RESULTS.md). Free space keeps ``h``, the step the arm's model integrates at.  Whether
    a world refines depends on its own state only, so each world's numbers stay its own
    whatever worlds share the batch."""
    for world in worlds:
        mujoco.mj_step1(world.model, world.data)  # positions, velocities, contacts
    touching = [i for i, world in enumerate(worlds) if world.data.ncon > 0]
    fine = [worlds[i] for i in touching]
    for world in fine:
        world.model.opt.timestep = world.physics_step / CONTACT_REFINE
    _second_half(worlds, tau)
    for _ in range(CONTACT_REFINE - 1 if fine else 0):
        for world in fine:
            mujoco.mj_step1(world.model, world.data)
        _second_half(fine, tau[touching])
    for world in fine:
        world.model.opt.timestep = world.physics_step


def _second_half(worlds: Sequence[MujocoWorld], tau: np.ndarray) -> None:
    """The second half of a physics step after ``mj_step1``: the URDF's joint damping and
    Bullet's link damping (:func:`link_damping`, all worlds at once) at the velocities the step
    starts from, as PyBullet applies them, with the torques ``tau: [n, dof]``, then
    ``mj_step2``."""
    first = worlds[0]
    wrench = link_damping(
        np.array([world._cvel for world in worlds]),
        np.array([world._com for world in worlds]),
        np.array([world._root_com for world in worlds]),
        np.array([world._R for world in worlds]),
        first._mass,
        first._inertia,
    )
    qvel = np.array([world._qvel[world._dofs] for world in worlds])
    applied = tau - first.damping * qvel
    for world, row, torque in zip(worlds, wrench, applied, strict=True):
        world._wrench[:] = row
        world._qfrc[world._dofs] = torque
        mujoco.mj_step2(world.model, world.data)
