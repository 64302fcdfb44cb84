"""The peg-insertion task as a Gymnasium environment, for other RL libraries.

Registered ids (both truncate after ``max_episode_steps = WorldConfig().T = 100`` steps; the
environment itself truncates after its own task's T, which a dataset's env spec repeats):

* ``lolgps_torch/PegInsertion-v0``: actions are torques (N m) in ``[-effort, effort]``;
* ``lolgps_torch/PegInsertionNormalized-v0``: the same with ``normalize_actions=True``,
  actions in ``[-1, 1]`` (float32, as RL libraries prefer) and torque ``u = action * effort``.

Observation: the state vector x (float64, ``dX = 2n + 12`` for an arm with n actuated joints,
see :class:`lolgps_torch.state.StateLayout`)::

    x = [ q (n) rad | qd (n) rad/s | p_tip - p*_tip (3) m | p_top - p*_top (3) m
          | v_tip (3) m/s | v_top (3) m/s ]

with the peg's tip and top points minus their targets at the bottom of the hole (world frame)
and the points' finite-difference velocities over the control step dt.

Action: torque on top of gravity compensation; the world applies
``clip(u + g(q), -effort, effort)``.  Reward: ``-l(x_t, u_t)``, the l12 + action cost of the
state before the step.  Step info: ``tip_distance`` (m) after the step, ``success``
(``tip_distance < success_threshold`` and no fault) and ``fault`` (None, or why the arm's
controller stopped the arm: a joint past its velocity limit or near a position limit, which
ends the episode as terminated, as it ends a real arm's motion; ``PlantConfig.limits``);
reset info: ``hole_offset``.

The observation space is bounded by limits that hold for every state of an episode of T steps
(:func:`observation_bounds`): PyBullet does not enforce URDF joint limits under torque control,
but Bullet clamps every joint speed at :data:`MAX_JOINT_VELOCITY`, which bounds ``qd`` and, over
T steps from ``q0``, ``q``; every point of the arm lies within the reach R of the base
(triangle inequality over the chain's fixed translations), and :meth:`PegInsertionEnv.reset`
refuses targets farther than R, so each point block is within ``2 R`` and each velocity block
within ``2 R / dt``.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.sim.simulator import WorldConfig
from lolgps_torch.task import PegTask, TaskConfig, task_config_from_dict

DEFAULT_URDF = str(Path(__file__).resolve().parent / "robot" / "data" / "kuka_peg.urdf")
ENV_ID = "lolgps_torch/PegInsertion-v0"
NORMALIZED_ENV_ID = "lolgps_torch/PegInsertionNormalized-v0"
# Bullet's default btMultiBody maximum joint velocity (rad/s): PyBullet clamps each joint to it.
MAX_JOINT_VELOCITY = 100.0


def reach(kinematics: PegKinematics) -> float:
    """An upper bound R (m) on the distance of the peg's points from the root link's origin:
    the sum of the norms of the chain's fixed joint and link translations and of the largest
    point offset (rotations keep lengths, so no configuration reaches farther)."""
    chain = kinematics.chain
    total = 0.0
    for name in chain.get_frame_names(exclude_fixed=False):
        frame = chain.find_frame(name)
        for offset in (frame.joint.offset, frame.link.offset):
            if offset is not None:
                total += float(offset.get_matrix()[0, :3, 3].norm())
    return total + float(kinematics.offsets.norm(dim=-1).max())


def observation_bounds(task: PegTask) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds ``[dX]`` of every observation within an episode of T steps
    (derivation in the module docstring)."""
    layout, world = task.layout, task.config.world
    R = reach(task.kinematics)
    high = np.empty(layout.dX)
    high[layout.qd] = MAX_JOINT_VELOCITY
    high[layout.points] = 2 * R
    high[layout.point_velocities] = 2 * R / world.dt
    high[layout.actions] = np.tile(task.arm.effort, layout.history)  # the past actions
    low = -high
    q0, swing = np.asarray(task.geometry.q0), MAX_JOINT_VELOCITY * world.T * world.dt
    low[layout.q], high[layout.q] = q0 - swing, q0 + swing
    return low, high


class PegInsertionEnv(gym.Env[np.ndarray, np.ndarray]):
    """One PyBullet world of the peg-insertion task (observation, action and reward in the
    module docstring).

    :param urdf: the arm's URDF (ignored when ``task_config`` is given).
    :param hole_range: without a reset option or ``hole_offset``, the hole offset is drawn
        uniformly in the square of this half-width (m) around the nominal position.
    :param ee_link: the end-effector link, detected when None (ignored with ``task_config``).
    :param task_config: the whole :class:`TaskConfig`, or it as a plain dict
        (``dataclasses.asdict``, as a run's config.json holds it), URDF path included: e.g.
        the task a stream run learns, scaled to the arm, placed and allowing for what the
        probes found, ``set_up(StreamSettings(task=...)).task``
        (:mod:`lolgps_torch.commands.stream`).
    :param hole_offset: a fixed hole offset (dx, dy) (m) for every reset without options.
    :param normalize_actions: actions in ``[-1, 1]``, scaled by the arm's efforts.

    ``reset(options={"hole_offset": (dx, dy)})`` puts the hole at that offset.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        urdf: str = DEFAULT_URDF,
        hole_range: float = 0.02,
        ee_link: str | None = None,
        task_config: TaskConfig | dict[str, Any] | None = None,
        hole_offset: tuple[float, float] | list[float] | None = None,
        normalize_actions: bool = False,
    ) -> None:
        if task_config is not None and (urdf != DEFAULT_URDF or ee_link is not None):
            raise LolgpsError("give either task_config or urdf/ee_link, not both")
        if task_config is None:
            config = TaskConfig(urdf=urdf, ee_link=ee_link)
        elif isinstance(task_config, TaskConfig):
            config = task_config
        else:
            config = task_config_from_dict(task_config)
        self.task = PegTask(config, n_worlds=1)
        self.world = self.task.sampler.worlds[0]
        self.hole_range = hole_range
        self.hole_offset = None if hole_offset is None else _pair(hole_offset)
        self.normalize_actions = normalize_actions
        self._reach = reach(self.task.kinematics)
        self.effort = np.asarray(self.task.arm.effort, dtype=np.float64)
        low, high = observation_bounds(self.task)
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float64)
        self.action_space: gym.spaces.Box = (
            gym.spaces.Box(-1.0, 1.0, (self.task.arm.dof,), dtype=np.float32)
            if normalize_actions
            else gym.spaces.Box(-self.effort, self.effort, dtype=np.float64)
        )
        self._t = 0
        self._targets = self.task.targets([(0.0, 0.0)])
        self._x = np.zeros(self.task.layout.dX)

    def spec_kwargs(self) -> dict[str, Any]:
        """JSON-able keyword arguments that rebuild this environment (the task as a dict)."""
        return {
            "task_config": asdict(self.task.config),
            "hole_range": self.hole_range,
            "hole_offset": None if self.hole_offset is None else list(self.hole_offset),
            "normalize_actions": self.normalize_actions,
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        if options and "hole_offset" in options:
            offset = _pair(options["hole_offset"])
        elif self.hole_offset is not None:
            offset = self.hole_offset
        else:
            offset = _pair(self.np_random.uniform(-self.hole_range, self.hole_range, size=2))
        self._targets = self.task.targets([offset])
        farthest = float(self._targets[0].norm(dim=-1).max())
        if farthest > self._reach:
            raise LolgpsError(
                f"hole offset ({offset[0]:+.3f}, {offset[1]:+.3f}) m puts the target "
                f"{farthest:.2f} m from the base, beyond the arm's reach {self._reach:.2f} m"
            )
        self.world.set_hole(offset)
        self._t = 0
        self._x = self.world.reset(np.asarray(self.task.geometry.q0))
        return self._x.copy(), {"hole_offset": offset}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        high = self.action_space.high.astype(np.float64)
        a = np.clip(np.asarray(action, dtype=np.float64), -high, high)
        u = a * self.effort if self.normalize_actions else a
        cost = self._cost(self._x, u, self._t)
        self._x = self.world.step(u)
        self._t += 1
        distance, fault = self.world.tip_distance(), self.world.fault
        info = {
            "tip_distance": distance,
            "success": distance < self.task.config.world.success_threshold and fault is None,
            "fault": fault,
        }
        return self._x.copy(), -cost, fault is not None, self._t >= self.task.T, info

    def _cost(self, x: np.ndarray, u: np.ndarray, t: int) -> float:
        """``l(x_t, u_t)`` as the task scores step t of a T-step rollout (its final multiplier
        and descending targets depend on t): the cost of x and u held over the horizon, at t."""
        T = self.task.T
        xs = torch.from_numpy(x).expand(1, T, x.shape[-1])
        us = torch.from_numpy(u).expand(1, T, u.shape[-1])
        return float(self.task.cost.evaluate(xs, us, self._targets[:, None])[0, min(t, T - 1)])

    def close(self) -> None:
        self.task.close()


def _pair(values: Any) -> tuple[float, float]:
    dx, dy = (float(v) for v in values)
    return dx, dy


gym.register(
    id=ENV_ID, entry_point="lolgps_torch.gym_env:PegInsertionEnv", max_episode_steps=WorldConfig().T
)
gym.register(
    id=NORMALIZED_ENV_ID,
    entry_point="lolgps_torch.gym_env:PegInsertionEnv",
    max_episode_steps=WorldConfig().T,
    kwargs={"normalize_actions": True},
)
