"""The peg-insertion task as a Gymnasium environment, for other RL libraries.

Observation: the state vector x (see :class:`lolgps_torch.state.StateLayout`).
Action: joint torques on top of gravity compensation, bounded by the URDF efforts.
Reward: ``-l(x_t, u_t)``, the l12 + action cost.  Episodes are truncated after T steps.
Registered as ``lolgps_torch/PegInsertion-v0``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from lolgps_torch.task import PegTask, TaskConfig

DEFAULT_URDF = str(Path(__file__).resolve().parents[1] / "robots" / "kuka_peg.urdf")


class PegInsertionEnv(gym.Env[np.ndarray, np.ndarray]):
    """One PyBullet world; the hole offset is drawn uniformly in a square of half-width
    ``hole_range`` (m) around the nominal position at each reset, or given in
    ``options={"hole_offset": (dx, dy)}``."""

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self, urdf: str = DEFAULT_URDF, hole_range: float = 0.02, ee_link: str | None = None
    ) -> None:
        self.task = PegTask(TaskConfig(urdf=urdf, ee_link=ee_link), n_worlds=1)
        self.world = self.task.sampler.worlds[0]
        self.hole_range = hole_range
        effort = np.asarray(self.task.arm.effort, dtype=np.float64)
        dX = self.task.layout.dX
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(dX,), dtype=np.float64)
        self.action_space: gym.spaces.Box = gym.spaces.Box(-effort, effort, dtype=np.float64)
        self._t = 0
        self._targets = self.task.targets([(0.0, 0.0)])

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if options and "hole_offset" in options:
            offset = tuple(float(v) for v in options["hole_offset"])
        else:
            offset = tuple(self.np_random.uniform(-self.hole_range, self.hole_range, size=2))
        self.world.set_hole((offset[0], offset[1]))
        self._targets = self.task.targets([(offset[0], offset[1])])
        self._t = 0
        obs = self.world.reset(np.asarray(self.task.geometry.q0))
        return obs, {"hole_offset": offset}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        u = np.clip(
            np.asarray(action, dtype=np.float64), self.action_space.low, self.action_space.high
        )
        x = torch.from_numpy(self.world.observe())[None, None]
        cost = self.task.cost.evaluate(x, torch.from_numpy(u)[None, None], self._targets[:, None])
        obs = self.world.step(u)
        self._t += 1
        distance = self.world.tip_distance()
        truncated = self._t >= self.task.T
        info = {
            "tip_distance": distance,
            "success": distance < self.task.config.world.success_threshold,
        }
        return obs, -float(cost), False, truncated, info

    def close(self) -> None:
        self.task.close()


gym.register(id="lolgps_torch/PegInsertion-v0", entry_point="lolgps_torch.gym_env:PegInsertionEnv")
