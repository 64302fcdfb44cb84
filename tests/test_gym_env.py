"""The Gymnasium environment passes Gymnasium's own checker and behaves like the task."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import asdict, replace

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from lolgps_torch.commands.stream import StreamSettings, set_up
from lolgps_torch.errors import LolgpsError
from lolgps_torch.gym_env import (
    DEFAULT_URDF,
    ENV_ID,
    NORMALIZED_ENV_ID,
    PegInsertionEnv,
    reach,
)
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.task import TaskConfig


@pytest.fixture(scope="module")
def normalized() -> Iterator[gym.Env[np.ndarray, np.ndarray]]:
    env = gym.make(NORMALIZED_ENV_ID)
    yield env
    env.close()


@pytest.fixture(scope="module")
def unlimited() -> Iterator[gym.Env[np.ndarray, np.ndarray]]:
    """The normalised environment on an arm whose controller lets it pass its limits."""
    config = TaskConfig(urdf=DEFAULT_URDF, plant=PlantConfig(limits="off"))
    env = gym.make(NORMALIZED_ENV_ID, task_config=asdict(config))
    yield env
    env.close()


@pytest.mark.filterwarnings("ignore:.*symmetric and normalized")  # torque actions, by design
def test_env_passes_gymnasium_checker() -> None:
    env = gym.make(ENV_ID)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_normalized_env_passes_the_checker_without_warnings(
    normalized: gym.Env[np.ndarray, np.ndarray],
) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(normalized.unwrapped, skip_render_check=True)
    assert [str(w.message) for w in caught] == []
    assert normalized.spec is not None and normalized.spec.max_episode_steps == 100
    space = normalized.action_space
    assert isinstance(space, gym.spaces.Box)
    assert space.dtype == np.float32 and space.shape == (7,)
    assert np.array_equal(space.low, -np.ones(7)) and np.array_equal(space.high, np.ones(7))


def test_full_effort_ends_the_episode_at_the_arms_limits(
    normalized: gym.Env[np.ndarray, np.ndarray],
) -> None:
    """Bang-bang actions at full effort pass a joint's velocity limit: the arm's controller
    stops the arm, and the episode ends, terminated, with the fault in its info and no
    success."""
    actions = np.random.default_rng(0).choice([-1.0, 1.0], size=(100, 7))
    normalized.reset(options={"hole_offset": (0.01, -0.01)})
    steps = 0
    for a in actions:
        obs, _, terminated, truncated, info = normalized.step(a)
        steps += 1
        assert normalized.observation_space.contains(obs)
        if terminated:
            break
    assert terminated and not truncated and steps < 10
    assert "velocity limit" in info["fault"] and not info["success"]


def test_rewards_are_the_task_costs_and_observations_stay_in_bounds(
    unlimited: gym.Env[np.ndarray, np.ndarray],
) -> None:
    """Without the arm's limits, bang-bang actions at full effort drive the joints to
    Bullet's speed clamp; every observation stays in the space, and the rewards and final
    distance are the task's own scoring of the same torques."""
    normalized = unlimited
    env = normalized.unwrapped
    assert isinstance(env, PegInsertionEnv)
    rng = np.random.default_rng(0)
    actions = rng.choice([-1.0, 1.0], size=(100, 7))
    obs, info = normalized.reset(options={"hole_offset": (0.01, -0.01)})
    assert info["hole_offset"] == (0.01, -0.01)
    rewards, states, truncated = [], [obs], False
    for a in actions:
        assert not truncated
        obs, reward, terminated, truncated, info = normalized.step(a)
        assert not terminated and normalized.observation_space.contains(obs)
        rewards.append(reward)
        states.append(obs)
    assert truncated
    assert np.abs(np.array(states)[:, 7:14]).max() > 50.0  # the velocity bound is exercised
    torques = torch.from_numpy(actions * env.effort)
    task = env.task.sample(lambda t, x, rows: torques[t][None], [(0.01, -0.01)])
    assert np.allclose(-np.array(rewards), task.cost[0].numpy(), rtol=1e-12, atol=0.0)
    assert np.allclose(np.array(states[:-1]), task.x[0].numpy(), rtol=0.0, atol=1e-9)
    assert np.allclose(states[-1], task.final_state[0].numpy(), rtol=0.0, atol=1e-9)
    tip = env.task.layout.points.start
    assert float(task.final_state[0, tip : tip + 3].norm()) == pytest.approx(
        float(task.final_distance[0]), abs=1e-12
    )
    assert info["tip_distance"] == pytest.approx(float(task.final_distance[0]), abs=1e-9)


def test_env_episode_is_truncated_and_rewards_are_costs() -> None:
    env = gym.make(ENV_ID)
    obs, info = env.reset(seed=0, options={"hole_offset": (0.0, 0.0)})
    assert info["hole_offset"] == (0.0, 0.0)
    steps, rewards, truncated = 0, [], False
    while not truncated:
        obs, reward, terminated, truncated, info = env.step(np.zeros(env.action_space.shape))
        rewards.append(reward)
        steps += 1
    assert steps == 100
    assert all(float(r) < 0 for r in rewards)
    assert info["tip_distance"] > 0.06 and not info["success"]  # holding the start pose
    env.close()


def test_task_config_kwarg_rebuilds_the_task_and_fixed_offset() -> None:
    config = TaskConfig(urdf=DEFAULT_URDF)
    config = replace(config, world=replace(config.world, T=5))
    env = PegInsertionEnv(task_config=asdict(config), hole_offset=(0.02, 0.02))
    assert env.task.config == config
    assert env.spec_kwargs()["task_config"] == asdict(config)
    _, info = env.reset(seed=3)
    assert info["hole_offset"] == (0.02, 0.02)
    truncations = [env.step(np.zeros(7))[3] for _ in range(5)]
    assert truncations == [False] * 4 + [True]
    with pytest.raises(LolgpsError, match="beyond the arm's reach"):
        env.reset(options={"hole_offset": (5.0, 0.0)})
    env.close()
    with pytest.raises(LolgpsError, match="either task_config or urdf"):
        PegInsertionEnv(urdf="other.urdf", task_config=asdict(config))


def test_reach_is_the_chain_length(normalized: gym.Env[np.ndarray, np.ndarray]) -> None:
    """The KUKA chain's joint translations (0.1575 ... 0.045 m), the peg (0.2 m) and the top
    point's offset (0.15 m), summed by hand from robots/kuka_peg.urdf."""
    env = normalized.unwrapped
    assert isinstance(env, PegInsertionEnv)
    by_hand = 0.1575 + 0.2025 + 0.2045 + 0.2155 + 0.1845 + 0.2155 + 0.081 + 0.045 + 0.2 + 0.15
    assert reach(env.task.kinematics) == pytest.approx(by_hand, abs=1e-8)  # float32 URDF parse


def test_the_env_takes_the_task_a_stream_run_learns() -> None:
    """The stream's set-up (the library call under ``lolgps run``) gives the environment its
    task: the hole and start pose placed for the stream's conditions."""
    settings = StreamSettings(
        task=TaskConfig(urdf=DEFAULT_URDF),
        conditions=((0.0, 0.0), (0.01, -0.01)),
        detect_gravity=False,
        detect_delay=False,
    )
    stream = set_up(settings)
    env = PegInsertionEnv(task_config=stream.task)
    assert env.task.config == stream.task
    assert env.spec_kwargs()["task_config"] == asdict(stream.task)
    observation, info = env.reset(options={"hole_offset": stream.conditions[1]})
    assert info["hole_offset"] == (0.01, -0.01)
    assert stream.task.placement.q0 is not None
    np.testing.assert_allclose(observation[env.task.layout.q], stream.task.placement.q0)
    env.close()
