"""The peg-insertion world, its kinematics and its cost, against independent answers."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator

import numpy as np
import pybullet_data
import pytest
import torch

from lolgps_torch.cost.l12 import CostConfig, PegCost, to_quadratic
from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.ik import follow, generic_rank, solve_ik
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import (
    PlacementConfig,
    place_task,
    reach,
    vertical_peg_targets,
)
from lolgps_torch.sim.rollout import linear_gaussian_actor
from lolgps_torch.sim.world import PegWorld
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian

KUKA = "robots/kuka_peg.urdf"
PANDA = os.path.join(pybullet_data.getDataPath(), "franka_panda/panda.urdf")
XARM = os.path.join(pybullet_data.getDataPath(), "xarm/xarm6_robot.urdf")


@pytest.fixture(scope="module")
def task() -> Iterator[PegTask]:
    t = PegTask(TaskConfig(urdf=KUKA), n_worlds=2)
    yield t
    t.close()


@pytest.mark.parametrize("urdf", [KUKA, PANDA, XARM])  # the peg included
def test_fk_matches_pybullet(urdf: str) -> None:
    arm = load_arm(urdf)
    kin = PegKinematics(arm)
    world = PegWorld(arm, TaskConfig(urdf=urdf).world, (0.6, 0.0, 0.2))
    rng = np.random.default_rng(0)
    lo, hi = np.array(arm.lower), np.array(arm.upper)
    qs = lo + (hi - lo) * rng.random((50, arm.dof))
    expected = []
    for q in qs:
        world.reset(q)
        expected.append(world.points())
    world.close()
    got = kin.points(torch.tensor(qs))
    assert torch.allclose(got, torch.tensor(np.stack(expected)), atol=1e-6, rtol=0)


def test_follow_may_pass_within_the_placement_margin_of_a_joint_limit(task: PegTask) -> None:
    """The margin keeps the placed poses off the limits; the way to a floor may use the whole
    range: with a joint's limit set just beyond where the path ends, the floor is reached."""
    kin, arm = task.kinematics, task.arm
    floor = task.targets([(0.02, -0.02)])
    q_end = _gauss_newton(kin, task.q0, floor)
    moved = int((q_end - task.q0).abs().argmax())
    span = arm.upper[moved] - arm.lower[moved]
    if float(q_end[moved]) > float(task.q0[moved]):  # the limit 1 % of the range beyond the end
        limits = {"upper": _set(arm.upper, moved, float(q_end[moved]) + 0.01 * span)}
    else:
        limits = {"lower": _set(arm.lower, moved, float(q_end[moved]) - 0.01 * span)}
    tight = dataclasses.replace(arm, **limits)
    error, _ = follow(kin, tight, task.q0, floor, 5)
    assert float(error[0]) < 1e-6


def _gauss_newton(kin: PegKinematics, q0: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """A pose reaching the point targets by minimum-norm Gauss-Newton steps from ``q0`` (so on
    q0's branch): where a way from q0 to the targets ends."""
    q = q0.clone()
    for _ in range(200):
        points, jac = kin.points_and_jacobian(q)
        e = targets.reshape(-1) - points.reshape(-1)
        q = q + torch.linalg.lstsq(jac, e).solution
    return q


def _set(values: tuple[float, ...], index: int, value: float) -> tuple[float, ...]:
    return tuple(value if i == index else v for i, v in enumerate(values))


def test_an_offset_out_of_reach_is_named(task: PegTask) -> None:
    task.check_reachable((0.02, -0.02))
    with pytest.raises(LolgpsError, match=r"^hole offset \(\+2\.000, \+0\.000\) m is out of the"):
        task.check_reachable((2.0, 0.0))


def test_follow_reaches_every_floor_from_q0_and_stops_short_beyond_reach(task: PegTask) -> None:
    kin, arm = task.kinematics, task.arm
    floors = task.targets([(0.02, -0.02), (-0.02, 0.02)])
    _, radius = reach(arm, kin)
    error, least = follow(kin, arm, task.q0, floors, 5)
    assert float(error.max()) < 1e-6
    assert float(least.min()) > 0.01 * radius
    beyond = vertical_peg_targets(
        torch.tensor([[2.0 * radius, 0.0, 0.0]], dtype=torch.float64), 0.15
    )
    error, least = follow(kin, arm, task.q0, beyond, 5)
    assert float(error[0]) > 0.5  # the arm stretches towards it and stops
    assert float(least[0]) < 0.01 * radius  # stretched: near a singular pose


def test_generic_rank_is_five_for_a_seven_joint_arm(task: PegTask) -> None:
    q = task.q0 + 0.3 * torch.randn(
        8, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0)
    )
    assert generic_rank(task.kinematics, q) == 5


@pytest.mark.slow  # the search over every candidate spot: 10 s and more
def test_a_stream_reachable_only_through_a_singular_pose_is_one_error(task: PegTask) -> None:
    # with the start pose given, no candidate hole solves its own: the same refusal, sooner
    q0 = tuple(task.q0.tolist())
    config = PlacementConfig(positions=((0.02, -0.02),), dexterity=0.9, q0=q0)
    with pytest.raises(LolgpsError, match=r"not all from the start pose without passing a singul"):
        place_task(task.arm, task.kinematics, config, task.config.world.depth)


def test_jacobian_matches_finite_differences(task: PegTask) -> None:
    kin = task.kinematics
    q = task.q0 + 0.3 * torch.randn(
        5, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(0)
    )
    eps = 1e-6
    eye = torch.eye(7, dtype=torch.float64)
    fd = torch.stack(
        [
            (kin.points(q + eps * eye[i]) - kin.points(q - eps * eye[i])).reshape(5, 6) / (2 * eps)
            for i in range(7)
        ],
        dim=-1,
    )
    assert torch.allclose(kin.jacobian(q), fd, atol=1e-8)


def _random_trajectories(
    task: PegTask, N: int, T: int, seed: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """States near q0 with random joint speeds (other dimensions zero), random actions, and
    one condition's targets."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.zeros(N, T, task.layout.dX, dtype=torch.float64)
    x[..., task.layout.q] = task.q0 + 0.2 * torch.randn(N, T, 7, dtype=torch.float64, generator=gen)
    u = torch.randn(N, T, task.layout.dU, dtype=torch.float64, generator=gen)
    x[..., task.layout.qd] = torch.randn(N, T, 7, dtype=torch.float64, generator=gen)
    return x, u, task.targets([(0.01, -0.02)])[0]


def test_cost_gradient_and_gauss_newton_hessian(task: PegTask) -> None:
    T, dX, dU = 3, task.layout.dX, task.layout.dU
    x, u, targets = _random_trajectories(task, 2, T, seed=1)
    e = task.cost.expand(x, u, targets)
    assert torch.allclose(e.value, task.cost.evaluate(x, u, targets))

    def total(y: torch.Tensor) -> torch.Tensor:
        return task.cost.evaluate(y[..., :dX], y[..., dX:], targets).sum()

    y = torch.cat([x, u], -1).requires_grad_(True)
    (grad,) = torch.autograd.grad(total(y), y)
    assert torch.allclose(torch.cat([e.lx, e.lu], -1), grad, atol=1e-8)

    # Gauss-Newton: the exact Hessian of l12(A(p(q_n) + J_n dq - p*)) in dq, which FD checks.
    q = x[0, 0, task.layout.q]
    p0, J = task.kinematics.points_and_jacobian(q)

    lifted = targets.clone()  # the descent schedule's targets at t = 0
    lifted[:, 2] += task.cost.config.descent_height

    def linearised(dq: torch.Tensor) -> torch.Tensor:
        d = p0.reshape(6) + J @ dq - lifted.reshape(6)
        return task.cost._l12(d @ task.cost.A.T)[0]

    H = torch.autograd.functional.hessian(linearised, torch.zeros(7, dtype=torch.float64))
    assert torch.allclose(e.lxx[0, 0][task.layout.q, task.layout.q], H, atol=1e-6)
    assert torch.allclose(e.luu[0, 0], torch.diag(task.cost.wu))
    qd = task.layout.qd  # the speed term: its curvature where a joint is past the free share
    velocity = torch.tensor(task.arm.velocity, dtype=torch.float64)
    wv = task.cost.config.speed_weight / velocity**2
    past = x[0, 0, qd].abs() > task.cost.config.speed_free * velocity
    assert task.cost.config.speed_weight > 0 and past.any() and not past.all()
    assert torch.allclose(e.lxx[0, 0][qd, qd], torch.diag(wv * past))

    quad = to_quadratic(e, x, u)  # exact at every sample when N = 1
    e1 = task.cost.expand(x[:1], u[:1], targets)
    quad1 = to_quadratic(e1, x[:1], u[:1])
    y1 = torch.cat([x[0], u[0]], -1)
    value = 0.5 * torch.einsum("ti,tij,tj->t", y1, quad1.C, y1) + (quad1.c * y1).sum(-1) + quad1.cc
    assert torch.allclose(value, e1.value[0])
    assert quad.C.shape == (T, dX + dU, dX + dU)


def test_descent_schedule_lifts_the_targets(task: PegTask) -> None:
    """With h_0 = 0.2 and t_d = 4 the cost is the plain cost with both targets raised by
    0.2, 0.15, 0.1, 0.05, 0, 0 m at steps 0-5, and its expansion is still the exact gradient."""
    effort = torch.tensor(task.arm.effort)
    lifted_cost = PegCost(
        CostConfig(descent_height=0.2, descent_steps=4), task.kinematics, task.layout, effort
    )
    plain_cost = PegCost(CostConfig(descent_height=0.0), task.kinematics, task.layout, effort)
    T, dX = 6, task.layout.dX
    x, u, targets = _random_trajectories(task, 2, T, seed=3)
    per_step = targets.expand(T, 2, 3).clone()
    per_step[..., 2] += torch.tensor([0.2, 0.15, 0.1, 0.05, 0.0, 0.0], dtype=torch.float64)[:, None]
    expected = plain_cost.evaluate(x, u, per_step)
    assert torch.allclose(lifted_cost.evaluate(x, u, targets), expected, rtol=1e-12)
    assert not torch.allclose(plain_cost.evaluate(x, u, targets), expected)
    e = lifted_cost.expand(x, u, targets)
    y = torch.cat([x, u], -1).requires_grad_(True)
    total = lifted_cost.evaluate(y[..., :dX], y[..., dX:], targets).sum()
    (grad,) = torch.autograd.grad(total, y)
    assert torch.allclose(torch.cat([e.lx, e.lu], -1), grad, atol=1e-8)


def test_state_points_agree_with_kinematics(task: PegTask) -> None:
    gen = torch.Generator().manual_seed(2)
    act = lambda t, x, rows: 2.0 * torch.randn(x.shape[0], 7, dtype=torch.float64, generator=gen)  # noqa: E731
    traj = task.sample(act, [(0.0, 0.0), (0.02, 0.02)])
    fk = (
        task.kinematics.points(traj.x[..., task.layout.q])
        - task.targets([(0.0, 0.0), (0.02, 0.02)])[:, None]
    )
    assert torch.allclose(traj.x[..., task.layout.points], fk.flatten(-2), atol=1e-6)
    vel = (
        traj.x[:, 1:, task.layout.points] - traj.x[:, :-1, task.layout.points]
    ) / task.config.world.dt
    assert torch.allclose(traj.x[:, 1:, task.layout.point_velocities], vel, atol=1e-9)


def test_gravity_compensation_holds_still(task: PegTask) -> None:
    zero = lambda t, x, rows: torch.zeros(x.shape[0], 7, dtype=torch.float64)  # noqa: E731
    traj = task.sample(zero, [(0.0, 0.0)])
    drift = (traj.x[0, :, task.layout.q] - task.q0).abs().max()
    assert drift < 1e-3


def _scripted_insertion(task: PegTask, shift: float) -> float:
    """Track a joint-space path q0 -> above the hole -> inserted, with the hole shifted in x."""
    targets = task.targets([(0.0, 0.0)])[0].clone()
    targets[:, 0] += shift
    above = targets.clone()
    above[:, 2] += 0.13
    q_above, _ = solve_ik(task.kinematics, task.arm, above, 0.0)
    q_in, _ = solve_ik(task.kinematics, task.arm, targets, 0.0)
    s = torch.linspace(0, 1, 40, dtype=torch.float64)[:, None]
    path = torch.cat(
        [task.q0 + (q_above - task.q0) * s, q_above + (q_in - q_above) * s, q_in.expand(20, -1)]
    )
    m = task.effective_inertia()
    kp, kd = 100.0 * m, 20.0 * m

    def act(t: int, x: torch.Tensor, rows: slice) -> torch.Tensor:
        return -kp * (x[:, task.layout.q] - path[t]) - kd * x[:, task.layout.qd]

    return float(task.sample(act, [(0.0, 0.0)]).final_distance[0])


def test_hole_is_insertable_and_tight(task: PegTask) -> None:
    assert _scripted_insertion(task, 0.0) < 0.02
    # 12 mm sideways, three times the mouth clearance: the peg rests on the table at the mouth
    assert _scripted_insertion(task, 0.012) > 0.09


def test_same_seed_gives_identical_trajectories(task: PegTask) -> None:
    dU, T = 7, task.T
    hold = LinearGaussian(
        torch.zeros(T, dU, task.layout.dX, dtype=torch.float64),
        torch.zeros(T, dU, dtype=torch.float64),
        torch.eye(dU, dtype=torch.float64).expand(T, dU, dU) * 4.0,
    )

    def run(seed: int) -> torch.Tensor:
        noise = torch.randn(
            2, T, dU, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)
        )
        return task.sample(linear_gaussian_actor(hold, noise), [(0.0, 0.0), (0.01, 0.0)]).x

    a, b = run(3), run(3)
    assert torch.equal(a, b)
    assert not torch.equal(a, run(4))
