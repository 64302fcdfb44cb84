"""The plant's departures from the URDF, each against PyBullet directly."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.model import ControlStep
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig
from lolgps_torch.task import TaskConfig, task_config_from_dict

KUKA = "robots/kuka_peg.urdf"
FAR = (0.0, 2.0, -1.0)  # a hole out of the arm's way


@pytest.fixture(scope="module")
def arm() -> ArmSpec:
    return load_arm(KUKA)


@pytest.fixture
def worlds() -> Iterator[list[PegWorld]]:
    made: list[PegWorld] = []
    yield made
    for world in made:
        world.close()


def _world(arm: ArmSpec, made: list[PegWorld], **plant: object) -> PegWorld:
    """A world of the plant ``plant`` that lets the arm pass its limits (the tests here push
    it hard to see the plant's other departures; tests/test_limits.py tests the limits)."""
    plant = {"limits": "off", **plant}
    world = PegWorld(arm, WorldConfig(), FAR, plant=PlantConfig(**plant))  # type: ignore[arg-type]
    made.append(world)
    return world


def _mass(world: PegWorld, link: int) -> float:
    return float(pb.getDynamicsInfo(world.body, link, physicsClientId=world.client)[0])


def _inverse_dynamics_at_rest(world: PegWorld, q: np.ndarray) -> np.ndarray:
    """PyBullet's gravity torque of the world's simulated body at the actuated angles q."""
    q_all = [0.0] * len(world.movable)
    for i, j in enumerate(world.actuated_in_movable):
        q_all[j] = float(q[i])
    zeros = [0.0] * len(q_all)
    g = pb.calculateInverseDynamics(world.body, q_all, zeros, zeros, physicsClientId=world.client)
    return np.asarray(g)[world.actuated_in_movable]


def test_payload_and_link_inertias(arm: ArmSpec, worlds: list[PegWorld]) -> None:
    nominal = _world(arm, worlds)
    scaled = _world(arm, worlds, inertia_scale=0.3, seed=5, payload=1.0)
    links = pb.getNumJoints(nominal.body, physicsClientId=nominal.client)
    factors = PlantConfig(inertia_scale=0.3, seed=5).link_factors(links)
    assert np.all((factors >= 0.7) & (factors <= 1.3)) and np.ptp(factors) > 0.1
    for link in range(links):
        added = 1.0 if link == nominal.peg_link_id else 0.0
        expected = _mass(nominal, link) * factors[link] + added
        assert _mass(scaled, link) == pytest.approx(expected, rel=1e-12, abs=1e-12)
        inertia = [
            np.asarray(pb.getDynamicsInfo(w.body, link, physicsClientId=w.client)[2])
            for w in (nominal, scaled)
        ]  # scaled, plus any isotropic rotor-like inertia a lighter link needs for stability
        raised = inertia[1] - inertia[0] * factors[link]
        assert raised.min() > -1e-12 and np.ptp(raised) < 1e-12


def test_gravity_compensation(arm: ArmSpec, worlds: list[PegWorld]) -> None:
    """plant: the simulated body's gravity torque (payload included); model: the URDF's; none."""
    q = np.asarray(arm.lower) * 0.3 + np.asarray(arm.upper) * 0.7
    nominal = _world(arm, worlds)
    modes = {
        m: _world(arm, worlds, payload=2.0, gravity_compensation=m)
        for m in ("plant", "model", "none")
    }
    for world in (nominal, *modes.values()):
        world.reset(q)
    plant = modes["plant"].gravity_compensation()
    np.testing.assert_allclose(plant, _inverse_dynamics_at_rest(modes["plant"], q), rtol=1e-12)
    np.testing.assert_allclose(
        modes["model"].gravity_compensation(), nominal.gravity_compensation()
    )
    assert np.abs(plant - nominal.gravity_compensation()).max() > 1.0  # 2 kg: newton metres
    assert not modes["none"].gravity_compensation().any()


def test_action_delay_is_the_commands_shifted(arm: ArmSpec, worlds: list[PegWorld]) -> None:
    """A delay of one control step acts as the undelayed world given (0, u_0, u_1, ...); one of a
    physics step, or a fraction of one, as PyBullet stepped by hand with each physics step's
    torque the mean over that step of the commands shifted by the delay."""
    q0 = np.asarray(arm.lower) * 0.5 + np.asarray(arm.upper) * 0.5
    rng = np.random.default_rng(0)
    commands = rng.normal(0.0, 5.0, (4, arm.dof))
    late = _world(arm, worlds, action_delay=0.05)
    prompt = _world(arm, worlds)
    late.reset(q0), prompt.reset(q0)
    shifted = np.concatenate([np.zeros((1, arm.dof)), commands[:-1]])
    for u, v in zip(commands, shifted, strict=True):
        np.testing.assert_array_equal(late.step(u), prompt.step(v))
    # 10 ms: one physics step; 15 ms: each physics step feels the mean of the commands of 1 and
    # 2 physics steps before; 2.5 ms: a quarter of the step before and the rest of this one
    for delay, weights in ((0.01, (0.0, 1.0)), (0.015, (0.0, 0.5, 0.5)), (0.0025, (0.75, 0.25))):
        _check_delayed_torques(arm, worlds, q0, commands, delay, weights)


def _check_delayed_torques(
    arm: ArmSpec,
    worlds: list[PegWorld],
    q0: np.ndarray,
    commands: np.ndarray,
    delay: float,
    weights: tuple[float, ...],
) -> None:
    """A world with commands ``delay`` s late against PyBullet stepped by hand, physics step s
    driven by ``sum_i weights[i] u(s - i)`` (u(s) the command issued for physics step s)."""
    world, prompt = _world(arm, worlds, action_delay=delay), _world(arm, worlds)
    world.reset(q0), prompt.reset(q0)
    substeps = prompt.config.substeps
    issued = np.concatenate([np.zeros((len(weights), arm.dof)), np.repeat(commands, substeps, 0)])
    for t, u in enumerate(commands):
        x = world.step(u)
        g = prompt.gravity_compensation()
        for s in range(substeps):
            now = len(weights) + t * substeps + s
            mean = sum(w * issued[now - i] for i, w in enumerate(weights))
            pb.setJointMotorControlArray(
                prompt.body,
                prompt.joint_ids,
                pb.TORQUE_CONTROL,
                forces=np.clip(mean + g, -prompt.effort, prompt.effort).tolist(),
                physicsClientId=prompt.client,
            )
            pb.stepSimulation(physicsClientId=prompt.client)
        moved = slice(0, 2 * arm.dof + 6)  # the point velocities differ by the reference
        np.testing.assert_allclose(x[moved], prompt.observe()[moved], rtol=0, atol=1e-12)


def test_joint_friction_holds_a_small_torque(arm: ArmSpec, worlds: list[PegWorld]) -> None:
    q0 = np.asarray(arm.lower) * 0.5 + np.asarray(arm.upper) * 0.5
    push = np.full(arm.dof, 2.0)
    held, free = _world(arm, worlds, joint_friction=3.0), _world(arm, worlds)
    held.reset(q0), free.reset(q0)
    for _ in range(5):
        x_held, x_free = held.step(push), free.step(push)
    assert np.abs(x_held[: arm.dof] - q0).max() < 1e-3
    assert np.abs(x_free[: arm.dof] - q0).min() > 1e-2


def test_observation_noise(arm: ArmSpec, worlds: list[PegWorld]) -> None:
    """Noise of 0.01 rad on the angles and 0.1 rad/s on the velocities, the points exact, the
    same for the same key and new for another."""
    q0 = np.asarray(arm.lower) * 0.5 + np.asarray(arm.upper) * 0.5
    noisy, exact = _world(arm, worlds, obs_noise=0.01), _world(arm, worlds)
    draws = np.stack([noisy.reset(q0, (k,)) - exact.reset(q0) for k in range(200)])
    n = arm.dof
    assert draws[:, :n].std() == pytest.approx(0.01, rel=0.1)
    assert draws[:, n : 2 * n].std() == pytest.approx(0.1, rel=0.1)
    assert not draws[:, 2 * n :].any()
    np.testing.assert_array_equal(noisy.reset(q0, (3,)), noisy.reset(q0, (3,)))


def test_bad_plants_are_refused() -> None:
    for bad in (
        {"inertia_scale": 1.0},
        {"payload": -1.0},
        {"gravity_compensation": "half"},
        {"obs_noise": float("nan")},
    ):
        with pytest.raises(LolgpsError):
            PlantConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(LolgpsError, match="action-delay"):
        PlantConfig(action_delay=-0.01)
    TaskConfig(urdf=KUKA, plant=PlantConfig(action_delay=0.015))  # any physical delay is taken
    assert WorldConfig(known_delay=0.012).delay_steps == 1  # the model's: the nearest step


def test_the_model_knows_the_delay(arm: ArmSpec, worlds: list[PegWorld]) -> None:
    """A world whose commands act 60 ms late (6 physics steps: u_{t-2} then u_{t-1} drive each
    control step) against its model told so: the state carries the last 2 actions, one model
    step changes the joint velocities as PyBullet does to 1 %, and the analytic linearisation
    is the autograd Jacobian."""
    config = WorldConfig(known_delay=0.06)
    world = PegWorld(arm, config, FAR, plant=PlantConfig(action_delay=0.06, limits="off"))
    worlds.append(world)
    layout, n = config.layout(arm.dof), arm.dof
    assert (layout.history, layout.dX) == (2, 4 * n + 12)
    rng = np.random.default_rng(1)
    x = [world.reset(np.asarray(arm.lower) * 0.45 + np.asarray(arm.upper) * 0.55)]
    commands = rng.normal(0.0, 3.0, (6, n))
    x += [world.step(u) for u in commands]
    states, actions = torch.as_tensor(np.stack(x)), torch.as_tensor(commands)
    np.testing.assert_allclose(
        x[-1][layout.actions], np.concatenate(commands[::-1][:2]), rtol=0, atol=1e-12
    )
    step = ControlStep(arm, config)
    predicted = step(states[:-1], actions)
    change = states[1:, n : 2 * n] - states[:-1, n : 2 * n]
    error = (predicted[:, n : 2 * n] - states[:-1, n : 2 * n] - change).norm(dim=-1)
    assert float((error / change.norm(dim=-1))[2:].max()) < 0.01
    torch.testing.assert_close(predicted[:, layout.actions], states[1:, layout.actions])
    F, f0 = step.linearize(states[3:5], actions[3:5])
    for i in range(2):
        Jx, Ju = torch.autograd.functional.jacobian(step, (states[3 + i], actions[3 + i]))
        torch.testing.assert_close(F[i], torch.cat([Jx, Ju], -1), rtol=1e-9, atol=1e-9)
    xu = torch.cat([states[3:5], actions[3:5]], -1)
    torch.testing.assert_close(
        (F @ xu[..., None]).squeeze(-1) + f0, step(states[3:5], actions[3:5])
    )


def test_the_plant_is_saved_with_the_task() -> None:
    """config.json's task (``asdict``) reads back with its plant, for evaluate.py and render.py."""
    task = TaskConfig(urdf=KUKA, plant=PlantConfig(payload=1.0, gravity_compensation="none"))
    assert task_config_from_dict(json.loads(json.dumps(dataclasses.asdict(task)))) == task


def test_a_bad_plant_flag_is_one_error_line(run_script: Callable[..., Any]) -> None:
    run = run_script("scripts/run_stream.py", "--plant-inertia-scale", "1.5", "--out", "/x/y")
    assert run.code == 2
    assert run.err.strip() == "error: --plant-inertia-scale must be in [0, 1), got 1.5"


@pytest.mark.parametrize("compensation", ["plant", "model", "none"])
def test_the_simulated_arms_own_model_predicts_it(compensation: str) -> None:
    """``PegTask.plant_model``, the model built from the true plant (each link's mass and
    inertia scaled, a payload, the compensation the plant applies and, with none, the
    learner's own), predicts the simulated arm's free transitions to rounding, where the
    URDF's model misses."""
    from lolgps_torch.controllers.noise import smoothed_noise
    from lolgps_torch.lolgps.local import LocalConfig, initial_controller
    from lolgps_torch.sim.rollout import linear_gaussian_actor
    from lolgps_torch.task import PegTask

    plant = PlantConfig(inertia_scale=0.3, seed=3, payload=1.0, gravity_compensation=compensation)  # type: ignore[arg-type]
    world = WorldConfig(compensate_gravity=compensation == "none")
    task = PegTask(TaskConfig(urdf=KUKA, world=world, plant=plant), n_worlds=2)
    try:
        noise = 0.3 * smoothed_noise(
            2, task.T, task.layout.dU, 2.0, torch.Generator().manual_seed(0)
        )
        hold = linear_gaussian_actor(initial_controller(task, LocalConfig()), noise)
        _, error_urdf, error_plant, transitions = task.one_step_errors(
            task.sample(hold, [(0.0, 0.0)] * 2)
        )
    finally:
        task.close()
    assert transitions >= 4
    assert error_plant < 1e-8 and error_urdf > 0.01
