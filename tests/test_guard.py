"""The policy's guard: bounds and brake fitted to a known system, the brake acting while a
bound is passed, the retreat tracked per rollout in the actor, and the guard's round trip
through a checkpoint."""

from __future__ import annotations

import math
import pickle
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import torch

from lolgps_torch.data.checkpoint import load_policy, save_policy
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, initial_controller
from lolgps_torch.lolgps.probes import noiseless_distance
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, policy_actor
from lolgps_torch.policy.actor import controller_actor
from lolgps_torch.policy.guard import Guard, fit_guard, guarded, within_limits
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.rollout import Rowwise, matmul_rows
from lolgps_torch.sim.simulator import WorldConfig
from lolgps_torch.state import StateLayout
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian

F64 = torch.float64
NO_HOVER = torch.full((2,), torch.nan, dtype=F64)
STILL = torch.zeros(4, dtype=torch.bool)  # no rollout steered to its hover point yet
ROOT = Path(__file__).resolve().parents[1]
LAYOUT = StateLayout(2)


def _known_system(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rollouts of ``q-dot_{t+1} = q-dot_t + B u_t + c`` with a known coupled ``B``."""
    g = torch.Generator().manual_seed(seed)
    B = torch.tensor([[0.5, 0.1], [0.1, 2.0]], dtype=F64)
    u = torch.randn(6, 20, 2, dtype=F64, generator=g)
    x = torch.zeros(6, 21, LAYOUT.dX, dtype=F64)
    for t in range(20):
        x[:, t + 1, LAYOUT.qd] = x[:, t, LAYOUT.qd] + u[:, t] @ B.T + 0.01
    return x, u, B


def test_the_bounds_are_margins_on_the_data() -> None:
    x, u, _ = _known_system()
    guard = fit_guard(x, 2.0 * u, LAYOUT, 1.3, 1.2, None, None, 0.5)
    assert float(guard.brake) == 0.5
    assert torch.allclose(guard.torque, 1.3 * 2.0 * u.abs().amax((0, 1)))
    assert torch.allclose(guard.speed, 1.2 * x[..., LAYOUT.qd].abs().amax((0, 1))[None])


def test_the_brake_takes_its_share_of_the_speeds_away_on_the_arm() -> None:
    """``stopping(x) = M(q) q-dot / dt`` row by row equals the batched mass matrix's product;
    in PyBullet's world (an independent answer: its own dynamics, gravity compensated), the
    brake's torque held over one control step slows the joint speeds that random torques gave
    the arm by at least beta (the joints' damping takes more), as the arm's model predicts."""
    free = PlantConfig(limits="off")  # pushed past the limits, to have speeds to take away
    task = PegTask(TaskConfig(str(ROOT / "robots" / "kuka_peg.urdf"), plant=free), n_worlds=3)
    try:
        lay, dt = task.layout, task.config.world.dt
        g = torch.Generator().manual_seed(5)
        push = 2.0 * torch.randn(3, 3, lay.dU, dtype=F64, generator=g)

        def act(t: int, x: torch.Tensor, rows: slice) -> torch.Tensor:
            return push[rows, t] if t < 3 else -0.5 * task.model.stopping(x)

        x = task.sampler.rollout(act, [(0.0, 0.0)] * 3).x
        before, after = x[:, 3], x[:, 4]
        q, qd = before[:, lay.q], before[:, lay.qd]
        batched = (task.model.urdf.mass_matrix(q) @ qd[..., None])[..., 0] / dt
        torch.testing.assert_close(task.model.stopping(before), batched, rtol=1e-12, atol=1e-12)
        assert float(qd.norm(dim=-1).amin()) > 0.5  # the arm moves
        assert (after[:, lay.qd].norm(dim=-1) < 0.5 * qd.norm(dim=-1)).all()
        predicted = task.model(before, -0.5 * task.model.stopping(before))
        torch.testing.assert_close(predicted[:, lay.qd], after[:, lay.qd], rtol=0, atol=1e-6)
    finally:
        task.close()


def test_the_hover_brake_steers_the_peg_above_a_far_hole_in_pybullet() -> None:
    """Braking with the hover (h, tau) from the start pose, every step, in PyBullet's world:
    both peg points come to rest within 2 cm of their targets raised by h, at a hole 0.25 m
    aside, where the plain brake leaves the arm at the start pose."""
    task = PegTask(TaskConfig(str(ROOT / "robots" / "kuka_peg.urdf")), n_worlds=2)
    try:
        lay, hover = task.layout, torch.tensor([0.15, 0.5], dtype=F64)
        raised = torch.zeros(6, dtype=F64)
        raised[2::3] = 0.15

        def steer(t: int, x: torch.Tensor, rows: slice) -> torch.Tensor:
            return -0.5 * task.model.stopping(x, hover)

        x = task.sampler.rollout(steer, [(0.0, 0.25), (-0.05, 0.1)]).x
        start = (x[:, 0, lay.points] - raised).norm(dim=-1)
        end = (x[:, -1, lay.points] - raised).norm(dim=-1)
        assert (start > 0.2).all() and (end < 0.02).all()
        assert (x[:, -1, lay.qd].abs() < 0.05).all()  # at rest
    finally:
        task.close()


def test_a_steered_rollout_brakes_until_it_reaches_its_hover_point() -> None:
    """With the hover, a row whose tip retreated past the bound goes on braking (steered)
    after the bound is no longer passed, until its tip is within 2 cm of the point h above
    its target; then the policy acts again. A speed passed stops the arm where it is, as
    without the hover, which remembers nothing."""
    hover = torch.tensor([0.1, 1.0], dtype=F64)
    guard = Guard(
        torch.full((2,), torch.inf, dtype=F64), torch.tensor([[1.0, 1.0]], dtype=F64),
        torch.tensor(1.0, dtype=F64), torch.tensor(0.04, dtype=F64), hover,
    )  # fmt: skip
    u = torch.full((4, 2), 0.5, dtype=F64)
    calls = []

    def stopping(x: torch.Tensor, hover: torch.Tensor | None = None) -> torch.Tensor:
        calls.append(hover)
        return torch.ones(x.shape[0], 2, dtype=F64)

    # row 0 retreats 0.2 m past its closest approach; row 1 is steered and far from its
    # hover point; row 2 is steered and within 2 cm of it (0.115 m above the target); row 3
    # passes a speed: it is stopped, not steered
    x = _states([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [2.0, 0.0]], [0.3, 0.3, 0.115, 0.3])
    steering = torch.tensor([False, True, True, False])
    closest = torch.tensor([0.1, 0.3, 0.115, 0.3], dtype=F64)
    out, _, after = guarded(u, x, LAYOUT, closest, steering, guard, 0, stopping)
    assert after.tolist() == [True, True, False, False]
    assert out.tolist() == [[-1.0, -1.0], [-1.0, -1.0], [0.5, 0.5], [-1.0, -1.0]]
    assert len(calls) == 2 and torch.equal(calls[0], hover) and calls[1] is None
    # nearer its target than the hover point, a row that trips is stopped where it is, not
    # pulled up, and is not steered afterwards
    low = _states([[0.0, 0.0], [0.0, 0.0]], [0.05, 0.05])
    out, _, after = guarded(u[:2], low, LAYOUT, torch.tensor([0.0, 0.05], dtype=F64),
                            torch.tensor([False, True]), guard, 0, stopping)  # fmt: skip
    assert after.tolist() == [False, False] and calls[-1] is None
    assert out.tolist() == [[-1.0, -1.0], [0.5, 0.5]]
    plain = guard._replace(hover=NO_HOVER)
    out, _, after = guarded(u, x, LAYOUT, torch.full((4,), torch.inf, dtype=F64), steering,
                            plain, 0, _speeds)  # fmt: skip
    assert not after.any() and torch.equal(out[:3], u[:3])  # never steered


def _states(qd: list[list[float]], distance: list[float]) -> torch.Tensor:
    """States with joint speeds ``qd`` and the tip ``distance`` (m) from its target along z."""
    x = torch.zeros(len(qd), LAYOUT.dX, dtype=F64)
    x[:, LAYOUT.qd] = torch.tensor(qd, dtype=F64)
    x[:, LAYOUT.points.start + 2] = torch.tensor(distance, dtype=F64)
    return x


@dataclass
class InertiaArm:
    """An arm model of constant mass matrix ``inertia`` and a control step of 1 s, with the
    given limits (:class:`ArmBrake`); its stopping torque ``inertia q-dot`` is computed row
    by row (:func:`matmul_rows`)."""

    inertia: torch.Tensor
    layout: StateLayout = LAYOUT
    velocity: torch.Tensor = torch.full((2,), torch.inf, dtype=F64)
    lower: torch.Tensor = torch.full((2,), -torch.inf, dtype=F64)
    upper: torch.Tensor = torch.full((2,), torch.inf, dtype=F64)
    dt: float = 1.0

    def stopping(self, x: torch.Tensor, hover: torch.Tensor | None = None) -> torch.Tensor:
        return matmul_rows(x[..., self.layout.qd], self.inertia)

    def mass_matrix(self, x: torch.Tensor) -> torch.Tensor:
        return self.inertia.expand(x.shape[0], *self.inertia.shape)

    def speed_change(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``dt M^-1 u``: the joint speeds' change under ``u`` in one step."""
        return torch.linalg.solve(self.inertia, u[..., None])[..., 0]


UNIT = InertiaArm(torch.eye(2, dtype=F64))


def _speeds(x: torch.Tensor) -> torch.Tensor:
    """The stopping torque of a two-joint arm of unit inertias and a control step of 1 s."""
    return UNIT.stopping(x)


def test_the_guard_bounds_torques_and_brakes_while_a_bound_is_passed() -> None:
    guard = Guard(
        torch.tensor([1.0, 2.0], dtype=F64),
        torch.tensor([[1.0, 1.0]], dtype=F64),
        torch.tensor(1.0, dtype=F64),
        torch.tensor(0.1, dtype=F64),
        torch.full((2,), torch.nan, dtype=F64),
    )
    u = torch.tensor([[5.0, -5.0], [0.5, 0.5], [0.5, 0.5], [0.5, 0.5]], dtype=F64)
    x = _states([[0.0, 0.0], [0.5, 1.5], [0.5, 0.5], [0.5, 0.5]], [0.3, 0.3, 0.3, 0.3])
    closest = torch.tensor([torch.inf, torch.inf, 0.15, 0.25], dtype=F64)
    out, nearest, _ = guarded(u, x, LAYOUT, closest, STILL, guard, 0, _speeds)
    # row 0 is clipped; row 1 passes a speed; row 2 has retreated 0.15 m > 0.1 m; row 3 0.05 m
    assert out.tolist() == [[1.0, -2.0], [-0.5, -1.5], [-0.5, -0.5], [0.5, 0.5]]
    assert nearest.tolist() == [0.3, 0.3, 0.15, 0.25]
    # nothing is latched: a slow state near its closest approach acts again
    slow = _states([[0.5, 0.5]] * 4, [0.2] * 4)
    assert torch.equal(guarded(u, slow, LAYOUT, nearest, STILL, guard, 1, _speeds)[0][1:], u[1:])
    off = Guard.off(2)
    assert torch.equal(guarded(u, x, LAYOUT, closest, STILL, off, 0, _speeds)[0], u)
    # per-step trip speeds: the same speeds pass at step 0 and brake at step 1
    stepped = guard._replace(speed=torch.tensor([[2.0, 2.0], [1.0, 1.0]], dtype=F64))
    fresh = torch.full((4,), torch.inf, dtype=F64)
    assert torch.equal(guarded(u, x, LAYOUT, fresh, STILL, stepped, 0, _speeds)[0][1], u[1])
    for t in (1, 7):
        assert torch.equal(
            guarded(u, x, LAYOUT, fresh, STILL, stepped, t, _speeds)[0][1],
            torch.tensor([-0.5, -1.5], dtype=F64),
        )


def test_the_actor_tracks_each_rollouts_closest_approach(tmp_path: Path) -> None:
    policy = GaussianPolicy(LAYOUT.dX, LAYOUT.dU)
    policy.set_guard(Guard(torch.full((2,), 1e6, dtype=F64), torch.ones(1, 2, dtype=F64),
                           torch.tensor(1.0, dtype=F64), torch.tensor(0.05, dtype=F64), NO_HOVER))  # fmt: skip
    actor = policy_actor(policy, UNIT)
    near, far = _states([[0.0, 0.0]] * 2, [0.1, 0.1]), _states([[0.0, 0.0]] * 2, [0.1, 0.2])
    actor(0, near, slice(0, 2))
    held = actor(1, far, slice(0, 2))
    assert torch.equal(held[1], torch.zeros(2, dtype=F64))  # 0.1 m back from 0.1: braking at rest
    assert not held[0].eq(0).all()  # the other rollout still acts
    assert not actor(0, far, slice(0, 2))[1].eq(0).all()  # a new rollout starts afresh
    fast = _states([[3.0, 0.0], [0.0, 0.0]], [0.1, 0.1])
    assert torch.equal(actor(1, fast, slice(0, 2))[0], torch.tensor([-3.0, 0.0], dtype=F64))
    # the actor crosses to worker processes, and the guard is saved with the policy
    assert isinstance(pickle.loads(pickle.dumps(actor)), type(actor))
    save_policy(tmp_path, policy)
    loaded = load_policy(tmp_path)
    for a, b in zip(loaded.guard, policy.guard, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)
    # per-step trip speeds round-trip too; a policy saved with one speed per joint (before
    # per-step speeds) loads as one row for every step, and one saved without a retreat
    # (before the retreat trip) with none
    per_step = torch.linspace(1.0, 2.0, 12, dtype=F64).reshape(6, 2)
    policy.set_guard(policy.guard._replace(speed=per_step))
    save_policy(tmp_path / "steps", policy)
    assert torch.equal(load_policy(tmp_path / "steps").guard.speed, per_step)
    state = {k: v for k, v in policy.state_dict().items() if k != "guard_retreat"}
    old = GaussianPolicy.from_state(
        policy.description(), {**state, "guard_speed": torch.ones(2, dtype=F64)}
    )
    assert torch.equal(old.guard.speed, torch.ones(1, 2, dtype=F64))
    assert torch.isinf(old.guard.retreat)
    # a policy saved with a fitted gain matrix (before the model's brake) brakes its share,
    # and one saved unguarded (a zero matrix) not at all
    for matrix, share in ((-torch.eye(2, dtype=F64), 0.5), (torch.zeros(2, 2, dtype=F64), 0.0)):
        braked = GaussianPolicy.from_state(policy.description(), {**state, "guard_brake": matrix})
        assert braked.guard.brake.shape == () and float(braked.guard.brake) == share


def test_the_rowwise_actor_gives_each_row_the_same_bits_in_any_batch() -> None:
    """The policy's row-wise form (a feedback head, random weights, the brake tripping on some
    rows, noise): each row's action is the same bits in batches of 1 to 12 rows at any place,
    and equals the policy's own (matrix-product) action to rounding."""
    dX, dU, n = 27, 7, 12
    policy = GaussianPolicy(dX, dU, PolicyConfig(hidden_sizes=(42, 42), feedback=True))
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():
        policy.gain.weight.normal_(0.0, 0.1, generator=g)
        policy.x_mean.normal_(generator=g)
        policy.x_std.uniform_(0.5, 2.0, generator=g)
    layout = StateLayout(dU)
    inertia = torch.randn(dU, dU, dtype=F64, generator=g)
    policy.set_guard(Guard(torch.full((dU,), 50.0, dtype=F64), torch.full((1, dU), 2.0, dtype=F64),
                           torch.tensor(0.5, dtype=F64), torch.tensor(0.05, dtype=F64), NO_HOVER))  # fmt: skip
    x = torch.randn(n, dX, dtype=F64, generator=g)
    x[::3, layout.qd] *= 4.0  # rows 0, 3, 6, 9 trip the brake
    noise = torch.randn(n, 3, dU, dtype=F64, generator=g)
    actor = policy_actor(policy, InertiaArm(inertia, layout, *_free(dU)), noise)
    assert isinstance(actor, Rowwise)
    alone = torch.cat([actor.rowwise()(2, x[i : i + 1], slice(i, i + 1)) for i in range(n)])
    for size in (2, 5, 12):
        for start in range(0, n - size + 1, 3):
            rows = slice(start, start + size)
            assert torch.equal(actor.rowwise()(2, x[rows], rows), alone[rows])
    torch.testing.assert_close(actor(2, x, slice(0, n)), alone, rtol=0, atol=1e-12)
    braked = (-0.5 * x[::3, layout.qd] @ inertia.T).clamp(-50.0, 50.0)
    torch.testing.assert_close(alone[::3], braked, rtol=0, atol=1e-12)  # the brake acts


def _free(dU: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Velocity and position limits that never bind, for ``dU`` joints."""
    inf = torch.full((dU,), torch.inf, dtype=F64)
    return inf, -inf, inf.clone()


def test_actions_are_scaled_to_keep_the_predicted_speeds_and_positions_within_limits() -> None:
    coupled = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=F64)
    one = torch.ones(2, dtype=F64)
    arm = InertiaArm(coupled, LAYOUT, one, -10 * one, 10 * one)  # v = 1 rad/s, |q| <= 10 rad
    x = _states([[0.0, 0.0], [0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [0.0, 0.0]], [0.1] * 5)
    x[4, LAYOUT.q] = torch.tensor([9.6, 0.0], dtype=F64)  # 0.3 rad from the bound at 10 - 0.1
    u = torch.tensor([[0.1, 0.1], [4.0, 0.0], [1.0, 0.0], [0.0, 0.0], [2.0, 0.0]], dtype=F64)
    out = within_limits(u, x, LAYOUT, arm, arm.mass_matrix(x), share=0.8, margin=0.1)
    after = x[:, LAYOUT.qd] + arm.speed_change(x, out)
    assert torch.equal(out[0], u[0])  # well within: untouched
    # scaled along u to the first bound met: the speed share, or 0.3 rad to go in 3 steps
    for row, bound in ((1, 0.8), (2, 0.8), (4, 0.1)):
        assert torch.allclose(out[row], out[row].norm() / u[row].norm() * u[row])
        assert float(after[row].abs().max()) == pytest.approx(bound)
    # row 3 coasts past 0.8 rad/s with no torque: braked back to the bound, the other joint kept
    assert torch.allclose(after[3], torch.tensor([0.8, 0.0], dtype=F64))
    # past the position bound a joint moves back: an action that does is kept, one that does
    # not gives way to the torque that stops the arm, moving that joint back to the bound
    x[4, LAYOUT.q] = torch.tensor([9.95, 0.0], dtype=F64)
    back = torch.tensor([[-0.2, 0.0]], dtype=F64)
    assert torch.equal(
        within_limits(back, x[4:], LAYOUT, arm, arm.mass_matrix(x[4:]), 0.8, 0.1), back
    )
    pushed = within_limits(-back, x[4:], LAYOUT, arm, arm.mass_matrix(x[4:]), 0.8, 0.1)
    assert float(arm.speed_change(x[4:], pushed)[0, 0]) == pytest.approx(-0.05 / 3)
    assert float(arm.speed_change(x[4:], pushed)[0, 1]) == pytest.approx(0.0)  # the arm stops
    # a joint without limits is never scaled
    free = InertiaArm(coupled, LAYOUT, *_free(2))
    assert torch.equal(within_limits(u, x, LAYOUT, free, free.mass_matrix(x), 0.8, 0.1), u)


def test_the_guard_keeps_a_flinging_policy_within_the_velocity_limits_in_pybullet() -> None:
    """A policy that asks for the arm's whole effort trips the arm's reflex on its first step;
    through the guard's limits it moves at most at the limit share, and no reflex fires."""
    config = TaskConfig(urdf=str(ROOT / "robots" / "kuka_peg.urdf"), world=WorldConfig(T=8))
    task = PegTask(config, n_worlds=1)
    try:
        effort = torch.tensor(task.arm.effort, dtype=F64)
        policy = GaussianPolicy(task.layout.dX, task.layout.dU)
        policy.set_guard(Guard.off(task.layout.dU))
        with torch.no_grad():
            policy.u_mean.copy_(effort * torch.tensor([1.0, -1.0] * 4)[: task.layout.dU])
            policy.u_scale.zero_()
        unguarded = GaussianPolicy(task.layout.dX, task.layout.dU, PolicyConfig(guard=False))
        unguarded.load_state_dict(policy.state_dict())
        flung = task.sample(policy_actor(unguarded, task.model), [(0.0, 0.0)])
        assert bool(flung.fault.all())
        kept = task.sample(policy_actor(policy, task.model), [(0.0, 0.0)])
        assert not bool(kept.fault.any())
        peak = (kept.x[..., task.layout.qd].abs() / task.model.velocity).amax()
        assert 0.3 < float(peak) <= 0.8 * 1.05
    finally:
        task.close()


def test_the_local_controllers_samples_are_kept_within_the_limits_in_pybullet() -> None:
    """A local controller asking for the arm's whole effort: its samples trip the arm's reflex
    on their first step; with the policy's limits (``PolicyConfig.limits``) they move at most
    at the limit share, no reflex fires, and the samples record the actions the arm was sent."""
    config = TaskConfig(urdf=str(ROOT / "robots" / "kuka_peg.urdf"), world=WorldConfig(T=8))
    task = PegTask(config, n_worlds=2)
    try:
        T, dX, dU = 8, task.layout.dX, task.layout.dU
        effort = torch.tensor(task.arm.effort, dtype=F64)
        flinging = LinearGaussian(
            torch.zeros(T, dU, dX, dtype=F64),
            (effort * torch.tensor([1.0, -1.0] * 4, dtype=F64)[:dU]).expand(T, dU),
            0.01 * torch.eye(dU, dtype=F64).expand(T, dU, dU),
        )
        local = LocalConfig(samples=2, model_plans=0)
        flung = LocalLearner(task, (0.0, 0.0), local, seed=0).sample(flinging)
        assert bool(flung.fault.all())
        limits = PolicyConfig().limits()
        assert limits == (0.8, 0.1) and PolicyConfig(guard=False).limits() is None
        kept = LocalLearner(task, (0.0, 0.0), local, seed=0, limits=limits).sample(flinging)
        assert not bool(kept.fault.any())
        peak = (kept.x[..., task.layout.qd].abs() / task.model.velocity).amax()
        assert 0.3 < float(peak) <= 0.8 * 1.05
        assert float((kept.u - flinging.k).abs().amax()) > 0.5 * float(effort.min())
        # the controller's noiseless check (which picks the teacher) is kept within them too
        before = task.arm_rollouts["probe"]
        assert noiseless_distance(task, flinging, (0.0, 0.0), None) == math.inf  # a fault
        assert math.isfinite(noiseless_distance(task, flinging, (0.0, 0.0), limits))
        assert task.arm_rollouts["probe"] == before + 2
    finally:
        task.close()


def test_the_arms_model_runs_what_the_arm_would_without_counting_as_the_arm() -> None:
    """``PegTask.simulate``: a simulated arm as the learner believes it is its own model, so its
    rollouts are the arm's, counted as the model's; an arm that carries a payload the learner
    is not told of is not, and its model moves as the unloaded arm does."""
    config = TaskConfig(urdf=str(ROOT / "robots" / "kuka_peg.urdf"), world=WorldConfig(T=8))
    loaded = replace(config, plant=PlantConfig(payload=2.0, gravity_compensation="model"))
    nominal, carrying = PegTask(config, n_worlds=2), PegTask(loaded, n_worlds=2)
    try:
        zero = torch.zeros(2, 8, nominal.layout.dU, dtype=F64)
        hold = controller_actor(
            initial_controller(nominal, LocalConfig()), zero, nominal.model, None
        )
        offsets = [(0.0, 0.0), (0.01, 0.0)]
        on_arm = nominal.sample(hold, offsets)
        on_model = nominal.simulate(hold, offsets)
        assert torch.equal(on_arm.x, on_model.x)
        assert nominal.arm_rollouts["sample"] == 2 and nominal.model_rollouts == 2
        assert sum(nominal.arm_rollouts.values()) == 2
        sagging = carrying.sample(hold, offsets)
        believed = carrying.simulate(hold, offsets)
        assert torch.allclose(believed.x, on_arm.x, atol=1e-9)
        assert float((sagging.x - on_arm.x).abs().amax()) > 1e-3
        assert sum(carrying.arm_rollouts.values()) == 2 and carrying.model_rollouts == 2
        assert carrying.model_faults == 0 == sum(carrying.arm_faults.values())
    finally:
        nominal.close()
        carrying.close()
