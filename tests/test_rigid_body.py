"""The arm's rigid-body dynamics and the world's control step in torch, against independent
answers: Pinocchio (analytic RNEA and CRBA from the same URDF text), PyBullet's own inverse
dynamics and mass matrix, PyBullet's simulation itself, and finite differences."""

from __future__ import annotations

import os
import tempfile

import numpy as np
import pinocchio as pin
import pybullet_data
import pytest
import torch

from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.model import ControlStep
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig

DATA = pybullet_data.getDataPath()
ARMS = {
    "kuka": os.path.join(os.path.dirname(__file__), "..", "robots", "kuka_peg.urdf"),
    "panda": os.path.join(DATA, "franka_panda", "panda.urdf"),
    "xarm6": os.path.join(DATA, "xarm", "xarm6_robot.urdf"),
}
PUBLISHED = os.path.join(os.path.dirname(__file__), "data", "arms")
CORPUS = [  # published descriptions as published: 6- and 5-DoF arms, grippers locked
    os.path.join(PUBLISHED, "armer_xarm/data/xacro/robots/xarm6/xarm6.urdf"),
    os.path.join(PUBLISHED, "trossen_descriptions/urdf/vx300s.urdf"),
    os.path.join(PUBLISHED, "trossen_descriptions/urdf/wx200.urdf"),
    os.path.join(DATA, "kuka_iiwa", "model.urdf"),
]
FAR = (5.0, 5.0, -3.0)  # a hole mouth far from every arm: free space


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Batches of tiny matrices: one thread is faster, and far faster on a loaded machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module", params=sorted(ARMS))
def arm(request: pytest.FixtureRequest) -> ArmSpec:
    return load_arm(ARMS[request.param])


def _pinocchio(arm: ArmSpec, locked: dict[str, float] | None = None) -> tuple:
    """Pinocchio's model of the arm's URDF with every non-actuated joint locked, the
    velocity indices of the actuated joints, and a function from q to Pinocchio's q."""
    full = pin.buildModelFromXML(arm.urdf_text)
    reference = pin.neutral(full)
    for name, value in (locked or {}).items():
        reference[full.joints[full.getJointId(name)].idx_q] = value
    lock = [full.getJointId(n) for n in list(full.names)[1:] if n not in arm.joint_names]
    model = pin.buildReducedModel(full, lock, reference)
    joints = [model.joints[model.getJointId(n)] for n in arm.joint_names]

    def to_pin(q: np.ndarray) -> np.ndarray:
        out = pin.neutral(model)
        for joint, value in zip(joints, q, strict=True):
            if joint.nq == 2:  # continuous joints are (cos, sin)
                out[joint.idx_q : joint.idx_q + 2] = [np.cos(value), np.sin(value)]
            else:
                out[joint.idx_q] = value
        return out

    return model, [j.idx_v for j in joints], to_pin


def _random_states(arm: ArmSpec, count: int, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    q = rng.uniform(arm.lower, arm.upper, (count, arm.dof))
    return q, rng.normal(size=(count, arm.dof)), rng.normal(size=(count, arm.dof))


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def _check_against_pinocchio(dyn: ArmDynamics, arm: ArmSpec, locked: dict | None = None) -> None:
    model, index, to_pin = _pinocchio(arm, locked)
    data = model.createData()
    q, qd, qdd = _random_states(arm, 16, seed=0)
    T = torch.as_tensor
    tau = dyn.inverse_dynamics(T(q), T(qd), T(qdd)).numpy()  # one batched call
    M = dyn.mass_matrix(T(q)).numpy()
    for i in range(len(q)):
        v, a = np.zeros(model.nv), np.zeros(model.nv)
        v[index], a[index] = qd[i], qdd[i]
        expected = pin.rnea(model, data, to_pin(q[i]), v, a)[index]
        full = pin.crba(model, data, to_pin(q[i]))
        expected_M = (np.triu(full) + np.triu(full, 1).T)[np.ix_(index, index)]
        assert _relative(tau[i], expected) < 1e-8
        assert _relative(M[i], expected_M) < 1e-8


def test_inverse_dynamics_and_mass_matrix_match_pinocchio(arm: ArmSpec) -> None:
    _check_against_pinocchio(ArmDynamics(arm), arm)


def test_pybullet_inertias_match_pybullet(arm: ArmSpec) -> None:
    """With the inertias PyBullet loads, RNEA and M equal calculateInverseDynamics and
    calculateMassMatrix (fingers and other locked joints at rest at 0)."""
    client = pb.connect(pb.DIRECT)
    pb.setGravity(0, 0, -9.81, physicsClientId=client)
    try:
        with tempfile.NamedTemporaryFile("w", suffix=".urdf", delete=False) as fh:
            fh.write(arm.urdf_text)
        body = pb.loadURDF(fh.name, useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE,
                           physicsClientId=client)  # fmt: skip
        os.unlink(fh.name)
        infos = [pb.getJointInfo(body, i, physicsClientId=client)
                 for i in range(pb.getNumJoints(body, physicsClientId=client))]  # fmt: skip
        movable = [i[1].decode() for i in infos if i[2] != pb.JOINT_FIXED]
        index = [movable.index(n) for n in arm.joint_names]
        dyn = ArmDynamics(arm, inertia="pybullet")
        q, qd, qdd = _random_states(arm, 8, seed=1)
        for i in range(len(q)):
            full = [np.zeros(len(movable)) for _ in range(3)]
            for vec, part in zip(full, (q[i], qd[i], qdd[i]), strict=True):
                vec[index] = part
            lists = [v.tolist() for v in full]
            tau = np.asarray(pb.calculateInverseDynamics(body, *lists, physicsClientId=client))
            M = np.asarray(pb.calculateMassMatrix(body, lists[0], physicsClientId=client))
            T = torch.as_tensor
            assert _relative(dyn.inverse_dynamics(T(q[i]), T(qd[i]), T(qdd[i])).numpy(),
                             tau[index]) < 1e-8  # fmt: skip
            assert _relative(dyn.mass_matrix(T(q[i])).numpy(), M[np.ix_(index, index)]) < 1e-8
    finally:
        pb.disconnect(client)


PRISMATIC_ARM = """<?xml version="1.0"?>
<robot name="slider">
  <link name="base"/>
  <link name="carriage"><inertial><origin xyz="0.01 0.02 0.05" rpy="0.1 0.2 0.3"/><mass value="2"/>
    <inertia ixx="0.02" ixy="0.001" ixz="0.002" iyy="0.03" iyz="0.001" izz="0.025"/></inertial></link>
  <link name="mount"><inertial><origin xyz="0 0.1 0"/><mass value="0.5"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.002" iyz="0" izz="0.001"/></inertial></link>
  <link name="arm"><inertial><origin xyz="0.2 0 0"/><mass value="1.5"/>
    <inertia ixx="0.004" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <link name="finger"><inertial><origin xyz="0.02 0 0"/><mass value="0.3"/>
    <inertia ixx="0.0005" ixy="0" ixz="0" iyy="0.0004" iyz="0" izz="0.0003"/></inertial></link>
  <link name="tip"><inertial><mass value="0.1"/>
    <inertia ixx="1e-4" ixy="0" ixz="0" iyy="1e-4" iyz="0" izz="1e-4"/></inertial></link>
  <joint name="lift" type="prismatic"><parent link="base"/><child link="carriage"/>
    <origin xyz="0 0 0.3" rpy="0.2 0 0"/><axis xyz="0 0.6 0.8"/>
    <limit lower="-0.5" upper="0.5" effort="100" velocity="1"/></joint>
  <joint name="mount_fixed" type="fixed"><parent link="carriage"/><child link="mount"/>
    <origin xyz="0 0 0.1" rpy="0 0.3 0"/></joint>
  <joint name="shoulder" type="revolute"><parent link="mount"/><child link="arm"/>
    <origin xyz="0.05 0 0.02" rpy="0 0 0.4"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="50" velocity="2"/></joint>
  <joint name="grip" type="prismatic"><parent link="arm"/><child link="finger"/>
    <origin xyz="0.3 0 0"/><axis xyz="0 0 1"/><limit lower="-0.05" upper="0.05" effort="5" velocity="1"/></joint>
  <joint name="elbow" type="continuous"><parent link="arm"/><child link="tip"/>
    <origin xyz="0.4 0 0" rpy="0.5 0 0"/><axis xyz="1 1 0"/><limit effort="20" velocity="2"/></joint>
</robot>
"""


def _slider_arm() -> ArmSpec:
    """:data:`PRISMATIC_ARM` with its lift, shoulder and elbow actuated."""
    return ArmSpec(urdf_text=PRISMATIC_ARM, source_path="slider.urdf", source_sha256="",
                  root_link="base", ee_link="tip", point_link="tip", peg_link="tip",
                  joint_names=("lift", "shoulder", "elbow"), lower=(-0.5, -2.0, -3.0),
                  upper=(0.5, 2.0, 3.0), effort=(100.0, 50.0, 20.0), velocity=(1.0, 2.0, 2.0),
                  point_offsets=((0.0, 0.0, 0.0), (0.0, 0.0, -0.1)), peg_radius=0.01)  # fmt: skip


def test_prismatic_fixed_and_locked_joints_match_pinocchio() -> None:
    """A chain with a prismatic joint, a fixed joint merged into its parent, a continuous joint,
    and a locked prismatic finger held away from 0."""
    arm = _slider_arm()
    locked = {"grip": 0.03}
    _check_against_pinocchio(ArmDynamics(arm, locked=locked), arm, locked)


def test_leading_dimensions_and_gradients() -> None:
    """[2, 3, n] batches give the per-state answers; gradients of forward and inverse
    dynamics match finite differences."""
    arm = load_arm(ARMS["kuka"])
    dyn = ArmDynamics(arm)
    q, qd, tau = (torch.as_tensor(a) for a in _random_states(arm, 6, seed=2))
    batched = dyn.forward_dynamics(q.view(2, 3, -1), qd.view(2, 3, -1), tau.view(2, 3, -1))
    single = torch.stack([dyn.forward_dynamics(q[i], qd[i], tau[i]) for i in range(6)])
    torch.testing.assert_close(batched.reshape(6, -1), single, rtol=1e-12, atol=1e-12)
    M = dyn.mass_matrix(q)
    torch.testing.assert_close(
        dyn.inverse_dynamics(q, qd, batched.reshape(6, -1)) - dyn.inverse_dynamics(q, qd, 0 * q),
        (M @ batched.reshape(6, -1, 1)).squeeze(-1), rtol=1e-10, atol=1e-10,
    )  # fmt: skip
    inputs = tuple(a[:2].clone().requires_grad_() for a in (q, qd, tau))
    assert torch.autograd.gradcheck(dyn.forward_dynamics, inputs)
    assert torch.autograd.gradcheck(dyn.inverse_dynamics, inputs)


@pytest.mark.parametrize("name", ["kuka", "slider"])
def test_inverse_dynamics_derivatives_match_autograd(name: str) -> None:
    """The analytic dtau/dq, dtau/dqd and M of the RNEA with Bullet's link damping as the
    external wrench equal the autograd Jacobians of ``inverse_dynamics_at`` (revolute,
    prismatic, fixed and locked joints); ``forward_dynamics_derivatives`` solves the same qdd
    and gives the same derivatives there."""
    arm = load_arm(ARMS["kuka"]) if name == "kuka" else _slider_arm()
    dyn = ArmDynamics(arm, locked={"grip": 0.03})
    q, qd, qdd = (torch.as_tensor(a) for a in _random_states(arm, 3, seed=8))

    def tau(q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor) -> torch.Tensor:
        frames = dyn.frames(q)
        return dyn.inverse_dynamics_at(frames, qd, qdd, dyn.link_damping(frames, qd, 0.3, 0.2))

    frames = dyn.frames(q)
    wrench, D = dyn.link_damping_with_jacobian(frames, qd, 0.3, 0.2)
    torch.testing.assert_close(wrench, dyn.link_damping(frames, qd, 0.3, 0.2))
    derivatives = dyn.inverse_dynamics_derivatives(frames, qd, qdd, wrench, D)
    tau_q = dyn.inverse_dynamics_at(frames, qd, qdd, wrench)
    solved, *at_solved = dyn.forward_dynamics_derivatives(frames, qd, tau_q, wrench, D)
    torch.testing.assert_close(solved, qdd, rtol=1e-10, atol=1e-10)
    for got, want in zip(at_solved, derivatives, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    for i in range(len(q)):
        expected = torch.autograd.functional.jacobian(tau, (q[i], qd[i], qdd[i]))
        for got, want in zip(derivatives, expected, strict=True):
            assert _relative(got[i].numpy(), want.numpy()) < 1e-12


def _smooth_torques(arm: ArmSpec, world: PegWorld, rng: np.random.Generator, steps: int):
    """Random smooth torques ``m_j a_j(t)``: sums of two sinusoids of 0.3 rad/s^2 accelerations
    per joint, scaled by each joint's effective inertia m_j (free motion of a few 0.1 rad)."""
    M = np.asarray(pb.calculateMassMatrix(world.body, world._q_all, physicsClientId=world.client))
    idx = world.actuated_in_movable
    m = 1.0 / np.diag(np.linalg.inv(M))[idx]
    t = np.arange(steps)[:, None] * world.config.dt
    freq, phase = rng.uniform(2.0, 5.0, (2, arm.dof)), rng.uniform(0, 2 * np.pi, (2, arm.dof))
    accel = 0.3 * (np.sin(freq[0] * t + phase[0]) + np.sin(freq[1] * t + phase[1]))
    return m * accel  # [steps, n]


def test_control_step_matches_pybullet(arm: ArmSpec) -> None:
    """From random free-space states, one step of f changes the joint velocities as PyBullet
    does to 1 %, and 50 steps of the same torques stay within 0.01 rad of PyBullet's."""
    config = WorldConfig()
    world = PegWorld(arm, config, FAR, plant=PlantConfig(limits="off"))  # pushed past them
    rng = np.random.default_rng(3)
    lower, upper = np.asarray(arm.lower), np.asarray(arm.upper)
    n, runs = arm.dof, []
    try:
        for _ in range(12):  # draws until 4 runs stay clear of the joint limits
            q0 = lower + (upper - lower) * rng.uniform(0.4, 0.6, n)
            qd0 = rng.normal(0.0, 0.1, n)
            for joint, qj, vj in zip(world.joint_ids, q0, qd0, strict=True):
                pb.resetJointState(world.body, joint, qj, vj, physicsClientId=world.client)
            states = [world.observe()]
            torques = _smooth_torques(arm, world, rng, 50)
            states += [world.step(u) for u in torques]
            q = np.stack(states)[:, :n]
            if np.minimum(q - lower, upper - q).min() > 0.05 and len(runs) < 4:
                runs.append((np.stack(states), torques))
    finally:
        world.close()
    assert len(runs) == 4
    x = torch.as_tensor(np.stack([r[0] for r in runs]))  # [4, 51, dX]
    u = torch.as_tensor(np.stack([r[1] for r in runs]))  # [4, 50, dU]
    step = ControlStep(arm, config)
    change = x[:, 1:, n : 2 * n] - x[:, :-1, n : 2 * n]
    predicted = step(x[:, :-1], u)[..., n : 2 * n] - x[:, :-1, n : 2 * n]
    error = (predicted - change).norm(dim=-1) / change.norm(dim=-1)
    assert float(error.max()) < 0.01
    rolled = x[:, 0]
    for t in range(50):
        rolled = step(rolled, u[:, t])
    assert float((rolled[:, :n] - x[:, -1, :n]).abs().max()) < 0.01
    torch.testing.assert_close(rolled[:, 2 * n :], x[:, -1, 2 * n :], rtol=0, atol=1e-3)


def test_control_step_gradients_match_finite_differences() -> None:
    arm = load_arm(ARMS["xarm6"])
    step = ControlStep(arm, WorldConfig(substeps=2))
    rng = np.random.default_rng(4)
    q, qd, u = (torch.as_tensor(a) for a in _random_states(arm, 1, seed=5))
    x = torch.cat([q, 0.3 * qd, torch.as_tensor(rng.normal(size=(1, 12)))], -1)
    assert torch.autograd.gradcheck(step, (x.requires_grad_(), (2 * u).requires_grad_()))
    # the analytic linearisation against central differences of f, column by column
    x, u = x.detach(), 2 * u
    F, _ = step.linearize(x, u)
    xu, eps = torch.cat([x, u], -1)[0], 1e-6
    for col in range(xu.shape[0]):
        plus, minus = xu.clone(), xu.clone()
        plus[col] += eps
        minus[col] -= eps
        dX = x.shape[-1]
        central = (step(plus[:dX], plus[dX:]) - step(minus[:dX], minus[dX:])) / (2 * eps)
        torch.testing.assert_close(F[0, :, col], central, rtol=1e-6, atol=1e-6)


def test_linearize_is_the_jacobian_of_the_step(arm: ArmSpec) -> None:
    """``ControlStep.linearize`` (analytic Jacobian over q, qd, u, point columns filled in)
    equals the reverse-mode autograd Jacobian of f to 1e-9 relative, with one joint's torque
    at its effort limit, and ``F [x; u] + f0 = f(x, u)``."""
    step = ControlStep(arm, WorldConfig())
    q, qd, u = (torch.as_tensor(a) for a in _random_states(arm, 3, seed=6))
    rng = np.random.default_rng(7)
    x = torch.cat([q, 0.3 * qd, torch.as_tensor(rng.normal(size=(3, 12)))], -1)
    u[2, 0] = 10 * step.effort[0]  # clipped: no derivative through this torque
    F, f0 = step.linearize(x, u)
    for i in range(3):
        Jx, Ju = torch.autograd.functional.jacobian(step, (x[i], u[i]))
        assert _relative(F[i].numpy(), torch.cat([Jx, Ju], -1).numpy()) < 1e-9
    assert float(F[2, :, x.shape[-1]].abs().max()) == 0.0
    xu = torch.cat([x, u], -1)
    torch.testing.assert_close((F @ xu[..., None]).squeeze(-1) + f0, step(x, u))


@pytest.mark.parametrize("path", CORPUS, ids=lambda p: os.path.basename(p))
def test_published_arms_match_pinocchio_and_pybullet(path: str) -> None:
    """On published descriptions: RNEA and M against Pinocchio, and one control step's joint
    velocity change against PyBullet's to 1e-6 relative."""
    arm = load_arm(path)
    _check_against_pinocchio(ArmDynamics(arm), arm)
    config = WorldConfig()
    world = PegWorld(arm, config, FAR)
    rng = np.random.default_rng(8)
    lower, upper, n = np.asarray(arm.lower), np.asarray(arm.upper), arm.dof
    try:
        q0 = lower + (upper - lower) * rng.uniform(0.4, 0.6, n)
        for joint, qj, vj in zip(world.joint_ids, q0, rng.normal(0.0, 0.1, n), strict=True):
            pb.resetJointState(world.body, joint, qj, vj, physicsClientId=world.client)
        x0 = torch.as_tensor(world.observe())
        u = _smooth_torques(arm, world, rng, 1)[0]
        x1 = torch.as_tensor(world.step(u))
    finally:
        world.close()
    predicted = ControlStep(arm, config)(x0, torch.as_tensor(u))
    change = x1[n : 2 * n] - x0[n : 2 * n]
    assert float((predicted[n : 2 * n] - x1[n : 2 * n]).norm() / change.norm()) < 1e-6
