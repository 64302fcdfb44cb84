"""A real arm behind the simulator seam (``--arm franka``): :class:`ArmWorld`, a
:class:`~lolgps_torch.sim.simulator.World` over a :class:`~lolgps_torch.sim.franka.RealArm`,
and :class:`ArmSampler`, the task's sampler with the one arm as its only world.

Each control step's command is held on the arm for ``dt``; the points and the learner's
compensation come from the learner's model of the arm (the ``--urdf`` or ``--mjcf`` given);
between rollouts the arm moves back to the start pose; between hole positions the person at
the arm is asked to move the hole (or it is taken as moved, ``--yes``).  A fault sets
:attr:`World.fault <lolgps_torch.sim.simulator.World.fault>`, as the simulated arm's reflex
does: the rollout ends there and counts as failed, the arm is recovered before the next one.
"""

from __future__ import annotations

import gc
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.franka import ArmFaultError, FrankaArm, RealArm, RealArmConfig
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.rollout import Sampler
from lolgps_torch.sim.simulator import World, WorldConfig


def connect(config: RealArmConfig, arm: ArmSpec) -> RealArm:
    """The real arm ``config`` names, connected (only the Franka so far)."""
    return FrankaArm(config, arm.effort)


class ArmWorld(World):
    """A :class:`World` whose arm is a real one (module docstring): one physics step a
    control step (``substeps`` 1), commanding the arm for ``dt``, the command held; the world's
    gravity compensation is the learner's model's (the arm adds its own: it only bounds the
    command within the effort limits); the arm's own reflexes, and the learner's
    (:class:`~lolgps_torch.sim.reflex.Reflex`, with ``--limits reflex``), end a rollout
    as a fault.

    :param real: the arm's settings. :param device: the arm, connected (:func:`connect`).
    """

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        real: RealArmConfig,
        device: RealArm,
        plant: PlantConfig = NOMINAL_PLANT,
    ) -> None:
        if replace(plant, limits=NOMINAL_PLANT.limits) != NOMINAL_PLANT:
            raise LolgpsError(
                "a real arm is as it is: the plant flags (--payload, --obs-noise, "
                "--action-delay, ...) simulate one and need --arm simulated"
            )
        super().__init__(arm, replace(config, substeps=1), nominal_mouth, plant)
        self.real, self.device = real, device
        self._dynamics = ArmDynamics(arm, config.gravity, "pybullet")
        self._kinematics = PegKinematics(arm)
        self._state = device.read_state()
        self._g = np.zeros(arm.dof)  # the learner's compensation at the control step's start
        self._hole: tuple[float, float] | None = None  # where the hole is taken to be
        self._rollouts = 0
        self._before = device.stats()  # the loop's figures when the rollout started
        self._moving = False  # under torque command since the last reset
        self._arm_stopped = False  # the arm's controller stopped it: to recover before it moves

    # the engine's primitives, on the arm

    def _move_hole(self, mouth: np.ndarray) -> None:
        """The person at the arm moves the hole (:meth:`set_hole`)."""

    def _set_joints(self, q: np.ndarray) -> None:
        """Bring the arm to rest at ``q``: recover it from its controller's fault, end the
        torque command, move slowly in joint space (also the learner's brake, where its own
        reflex stops a rollout)."""
        try:
            if self._arm_stopped:
                self.device.recover()
                self._arm_stopped = False
            self.device.stop()
            self._state = self.device.move_to(q, self.real.move_speed)
        except ArmFaultError as error:
            raise LolgpsError(
                f"the arm could not be brought to the start pose: {error.reason} (the run "
                "continues from its last finished condition with --resume)"
            ) from None
        self._moving = False

    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self._state.q, self._state.dq

    def _point_pose(self) -> tuple[np.ndarray, np.ndarray]:
        q = torch.from_numpy(np.asarray(self._state.q, dtype=np.float64))
        m = self._kinematics.chain.forward_kinematics(q[None]).get_matrix()[0].numpy()
        return m[:3, 3], m[:3, :3]

    def _physics_step(self, tau: np.ndarray) -> None:
        """Command ``tau - g`` (the arm adds its own g) for the control step, ``dt`` (the
        world's one physics step: the arm's loop does the ticks); nothing once the arm has
        faulted.  A fault ends the rollout (:attr:`fault`), said in one line."""
        if self.fault is not None:
            return
        try:
            self._state = self.device.command_torque(tau - self._g, self.config.dt)
            self._moving = True
        except ArmFaultError as error:
            self._state, self.fault = error.state, f"the arm stopped: {error.reason}"
            self._arm_stopped = True
            print(f"rollout {self._rollouts + 1}: {self.fault}; it counts as failed", flush=True)

    def gravity_compensation(self) -> np.ndarray:
        q = torch.from_numpy(np.asarray(self._observed_q, dtype=np.float64))
        self._g = self._dynamics.gravity_torque(q).numpy()
        return self._g

    def effective_inertia(self, q: Sequence[float]) -> Tensor:
        M = self._dynamics.mass_matrix(torch.tensor(q, dtype=torch.float64))
        return 1.0 / torch.diagonal(torch.linalg.inv(M))

    def joint_damping(self) -> Tensor:
        return self._dynamics.joint_damping.clone()

    def close(self) -> None:
        gc.enable()
        self.device.close()

    # the interface's rollout on the arm

    def set_hole(self, offset: tuple[float, float]) -> None:
        """Have the hole at ``offset``: where it is not there yet, the person at the arm moves
        it and presses Enter (or it is taken as moved, :attr:`RealArmConfig.yes`)."""
        offset = (float(offset[0]), float(offset[1]))
        if offset != self._hole:
            mouth = self.nominal_mouth + np.array([offset[0], offset[1], 0.0])
            where = ", ".join(f"{v:.4f}" for v in mouth)
            line = (
                f"hole at offset ({offset[0]:+.4f}, {offset[1]:+.4f}) m: its mouth's centre at "
                f"({where}) m in the arm's base frame"
            )
            if self.real.yes:
                print(f"{line} (taken as set: --yes)")
            else:
                self._stop_arm()
                try:
                    input(f"{line}; move it there and press Enter ")
                except EOFError:
                    raise LolgpsError(
                        "--arm franka waits for Enter once the hole is moved, and the input "
                        "has ended: pass --yes with the measured offsets as the conditions"
                    ) from None
            self._hole = offset
        super().set_hole(offset)

    def _stop_arm(self) -> None:
        """End a torque command left running, and let the garbage collector run again."""
        gc.enable()
        if self._moving:
            try:
                self._state = self.device.stop()
            except ArmFaultError as error:
                self.fault = f"the arm stopped: {error.reason}"
                self._arm_stopped = True
            self._moving = False

    def reset(self, q0: np.ndarray, key: tuple[int, ...] = (0,)) -> np.ndarray:
        """Recover the arm if it faulted, move it to ``q0`` slowly, and return the state.
        The garbage collector runs now, while the arm rests, and not again until the rollout
        ends: a collection of the learner's heap can pause it past the deadline."""
        self._before = self.device.stats()
        state = super().reset(q0, key)
        gc.collect()
        gc.disable()
        return state

    def step(self, u: np.ndarray) -> np.ndarray:
        """:meth:`World.step` on the arm; after the episode's last step the torque command
        ends and the rollout is reported in one line (the arm's seconds, missed ticks)."""
        state = super().step(u)
        if self._steps == self.config.T:
            self._stop_arm()
            self._report()
        return state

    def _report(self) -> None:
        self._rollouts += 1
        now, before = self.device.stats(), self._before
        ticks, missed = now.ticks - before.ticks, now.missed - before.missed
        outcome = self.fault or f"tip {self.tip_distance():.4f} m from the hole's floor"
        print(
            f"rollout {self._rollouts} on the arm: {now.torque_seconds - before.torque_seconds:.2f}"
            f" s under torque, {now.move_seconds - before.move_seconds:.2f} s moving to the "
            f"start before it; {missed} of {ticks + missed} ticks missed; {outcome}",
            flush=True,
        )


class ArmSampler(Sampler):
    """The task's sampler on the one real arm: a single world, the arm's (rollouts run one
    at a time, however many the caller would step together)."""

    def __init__(
        self,
        real: RealArmConfig,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        q0: Sequence[float],
        device: torch.device | str = "cpu",
        plant: PlantConfig = NOMINAL_PLANT,
    ) -> None:
        self.real, self.arm, self.mouth, self.plant = real, arm, nominal_mouth, plant
        super().__init__(arm, config, nominal_mouth, q0, 1, device)

    def seconds(self) -> float:
        """The arm's seconds so far under torque command and moving to a start pose (0
        before its first rollout)."""
        world = self.worlds[0] if self.worlds else None
        if not isinstance(world, ArmWorld):
            return 0.0
        stats = world.device.stats()
        return stats.torque_seconds + stats.move_seconds

    def grow(self, n_worlds: int) -> None:
        """The arm's world, once."""
        if not self.worlds:
            device = connect(self.real, self.arm)
            world = ArmWorld(self.arm, self.config, self.mouth, self.real, device, self.plant)
            self.worlds.append(world)
