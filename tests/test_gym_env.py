"""The Gymnasium environment passes Gymnasium's own checker and behaves like the task."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.utils.env_checker import check_env

import lolgps_torch.gym_env  # noqa: F401  (registers the id)


def test_env_passes_gymnasium_checker() -> None:
    env = gym.make("lolgps_torch/PegInsertion-v0")
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_env_episode_is_truncated_and_rewards_are_costs() -> None:
    env = gym.make("lolgps_torch/PegInsertion-v0")
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
