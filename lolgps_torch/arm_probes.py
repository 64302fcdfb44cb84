"""The arm probed before learning, and the task fitted to what is found: the stream's geometry
scaled to the arm's reach (:func:`fit_scale`), the arm's command delay (:func:`measure_delay`)
and whether it compensates its commands for gravity (:func:`measure_gravity`), each probe in a
world of its own (:func:`probe_world`), the task's worlds and random streams untouched."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace

import numpy as np

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import Spots, pinned, place_task, reach
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.robot.validate import ArmWarning
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.gravity import GravityConfig, GravityEstimate, estimate_gravity, let_go
from lolgps_torch.sim.latency import DelayConfig, DelayEstimate, estimate_delay, excite
from lolgps_torch.sim.simulator import World
from lolgps_torch.task import TaskConfig, load_task_arm

# Reach (m) of the arm the default geometry is made for (robots/kuka_peg.urdf, from the shoulder)
REFERENCE_REACH = 1.15
_SHRINK = 0.8  # each further try of --scale auto
_TRIES = 4


def scaled(config: TaskConfig, factor: float) -> TaskConfig:
    """``config`` with the stream's geometry scaled by ``factor`` (relative to its own scale):
    the hole positions the placement reaches, the start pose's offset from the hole and the
    length of the peg attached to arms that carry none (a URDF's own peg stays)."""
    placement = replace(
        config.placement,
        positions=tuple((dx * factor, dy * factor) for dx, dy in config.placement.positions),
        start_offset=tuple(v * factor for v in config.placement.start_offset),  # type: ignore[arg-type]
    )
    peg = replace(config.peg, length=config.peg.length * factor)
    return replace(config, scale=config.scale * factor, placement=placement, peg=peg)


def fit_scale(config: TaskConfig) -> tuple[TaskConfig, str]:
    """``config`` as it is if the placement fits its geometry (the stream's positions in
    ``config.placement``) to the arm, else scaled (:func:`scaled`) to fit: by the arm's reach
    over :data:`REFERENCE_REACH`, then by :data:`_SHRINK` at each further try; the placement's
    spots about the sampled tips are searched only where its grid fits no scale.  Returns the
    config, its placement pinned (the hole and start pose found), and a line saying what was
    scaled ("" when nothing was); a :class:`LolgpsError` when no try fits (the one that says
    why the geometry as given does not).
    The arm's warnings are left to the task built from the result (one set, not one a try)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        return _fit_scale(config)


def _fit_scale(config: TaskConfig) -> tuple[TaskConfig, str]:
    """:func:`fit_scale`, its warnings not silenced: each scale with the placement's grid of
    spots first, then each with the spots about the arm's sampled tips (so that an arm the grid
    places, at some scale, is placed as it was)."""
    arm = load_task_arm(config)
    kinematics = PegKinematics(arm)
    try:
        return _pinned(config, arm, kinematics, "grid"), ""
    except LolgpsError as error:
        unscaled = error
    radius = reach(arm, kinematics)[1]
    factor = min(1.0, radius / REFERENCE_REACH)
    tries = [scaled(config, factor * _SHRINK**attempt) for attempt in range(_TRIES)]
    passes: tuple[tuple[Spots, list[TaskConfig]], ...] = (
        ("grid", tries),
        ("sampled", [config, *tries]),
    )
    for spots, candidates in passes:
        for candidate in candidates:
            arm = load_task_arm(candidate)
            try:
                placed = _pinned(candidate, arm, PegKinematics(arm), spots)
            except LolgpsError:
                continue
            if placed.scale == config.scale:
                return placed, ""
            return placed, (
                f"the default geometry does not fit this arm's reach ({radius:.2f} m): hole "
                f"offsets, test areas, start height and attached peg scaled by "
                f"{placed.scale:.3g} (--scale)"
            )
    raise unscaled from None


def _pinned(
    config: TaskConfig, arm: ArmSpec, kinematics: PegKinematics, spots: Spots
) -> TaskConfig:
    """``config`` with its placement pinned where :func:`place_task` puts the hole."""
    geometry = place_task(arm, kinematics, config.placement, config.world.depth, spots)
    return replace(config, placement=pinned(config.placement, geometry))


@contextmanager
def probe_world(config: TaskConfig) -> Iterator[tuple[World, np.ndarray]]:
    """A world of its own for probing the arm ``config`` describes before learning, its hole
    at offset zero, and the start pose q0: the task's worlds and random streams stay
    untouched. Closed on leaving the context."""
    arm = load_task_arm(config)
    geometry = place_task(arm, PegKinematics(arm), config.placement, config.world.depth)
    world = build_world(config.sim, arm, config.world, geometry.nominal_mouth, config.plant)
    try:
        world.set_hole((0.0, 0.0))
        yield world, np.asarray(geometry.q0, dtype=np.float64)
    finally:
        world.close()


def measure_delay(config: TaskConfig, settings: DelayConfig) -> DelayEstimate:
    """The command delay of the arm ``config`` describes, estimated from excitation rollouts at
    its start pose (:mod:`lolgps_torch.sim.latency`) in a :func:`probe_world`."""
    with probe_world(config) as (world, q0):
        data = excite(world, q0, settings)
    return estimate_delay(data, config.world.dt, config.world.substeps, settings.longest)


def measure_gravity(config: TaskConfig, settings: GravityConfig) -> GravityEstimate:
    """Whether the arm ``config`` describes compensates its commands for gravity, from
    rollouts let go at its start pose (:mod:`lolgps_torch.sim.gravity`) in a
    :func:`probe_world` without the learner's own compensation."""
    world_config = replace(config.world, compensate_gravity=False)
    with probe_world(replace(config, world=world_config)) as (world, q0):
        moves = let_go(world, q0, settings)
        inertia = world.effective_inertia(q0.tolist()).numpy()
        arm = world.arm
    return estimate_gravity(moves, arm, world_config, inertia)
