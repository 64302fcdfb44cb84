"""The engines behind the simulator seam: a world, a display and the errors of each.

:mod:`.simulator` is the interface alone; this module picks the engine that implements it, so
that the engines import the interface and nothing imports back.
"""

from __future__ import annotations

import numpy as np

from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.pybullet_display import PyBulletDisplay
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.simulator import Display, Simulator, World, WorldConfig, require
from lolgps_torch.sim.world import PegWorld


def build_world(
    simulator: Simulator,
    arm: ArmSpec,
    config: WorldConfig,
    nominal_mouth: tuple[float, ...],
    plant: PlantConfig = NOMINAL_PLANT,
) -> World:
    """A world of ``simulator``'s engine (:func:`require` checks that it is installed)."""
    require(simulator)
    if simulator == "mujoco":
        from lolgps_torch.sim.mujoco_world import MujocoWorld  # only where MuJoCo is installed

        return MujocoWorld(arm, config, nominal_mouth, plant)
    return PegWorld(arm, config, nominal_mouth, plant=plant)


def build_display(
    arm: ArmSpec, config: WorldConfig, nominal_mouth: tuple[float, ...], cut: np.ndarray | None
) -> Display:
    """The display of the arm (any simulator's run: no physics runs in it, so PyBullet's CPU
    renderer draws every run); ``cut``: leave out the hole's boxes whose centre lies on this
    horizontal direction's side of the hole's axis (None: draw all)."""
    return PyBulletDisplay(arm, config, nominal_mouth, cut)


def engine_errors(simulator: Simulator) -> tuple[type[Exception], ...]:
    """The exceptions ``simulator``'s engine raises for a body it cannot build or step."""
    if simulator == "mujoco":
        return (ValueError,)
    return (pb.error,)
