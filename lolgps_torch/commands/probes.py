"""The probes a stream runs on the arm before learning (``lolgps run``, scripts/
train_condition.py): whether its commands are compensated for gravity, and how late they act;
what either finding changes in the task and the local learner, and the rollouts they take."""

from __future__ import annotations

import dataclasses

from lolgps_torch.arm_probes import measure_delay, measure_gravity
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.sim.gravity import GravityConfig
from lolgps_torch.sim.latency import DelayConfig
from lolgps_torch.task import TaskConfig


def detect_delay(task: TaskConfig, enabled: bool) -> float:
    """The arm's command delay (s) estimated from excitation rollouts at the start pose
    (:func:`~lolgps_torch.arm_probes.measure_delay`), said in one line when not zero; 0 when not
    ``enabled`` or when the task already allows for a known delay."""
    if not delay_probed(task, enabled):
        return 0.0
    settings = DelayConfig()
    estimate = measure_delay(task, settings)
    if estimate.steps:
        print(
            f"the arm's commands act {estimate.seconds * 1000:.0f} ms late (estimated from "
            f"{settings.rollouts} excitation rollouts): the learner allows for it "
            "(--known-delay; --no-detect-delay to learn without)"
        )
    return estimate.seconds


def delay_probed(task: TaskConfig, enabled: bool) -> bool:
    """Whether :func:`detect_delay` rolls the arm out: ``enabled`` and no known delay."""
    return enabled and task.world.known_delay <= 0.0


def gravity_probed(task: TaskConfig, enabled: bool) -> bool:
    """Whether :func:`detect_gravity` rolls the arm out: ``enabled`` and the learner does not
    compensate gravity already."""
    return enabled and not task.world.compensate_gravity


def start_rollouts(task: TaskConfig, gravity: bool, delay: bool) -> int:
    """The rollouts on the arm before the stream: :func:`detect_gravity`'s (``gravity``
    enabled) and :func:`detect_delay`'s (``delay`` enabled) on ``task``."""
    return GravityConfig().rollouts * gravity_probed(task, gravity) + DelayConfig().rollouts * (
        delay_probed(task, delay)
    )


def allow_for_delay(
    task: TaskConfig, local: LocalConfig, seconds: float
) -> tuple[TaskConfig, LocalConfig]:
    """The task and local learner allowing for a command delay of ``seconds``: the known delay
    (the state carries the last actions, the model acts on each command late), and from half a
    control step on the hold as the first controller (``--model-plans 0``: a controller
    planned on the model shakes in contact 40 or 50 ms late, docs/RESULTS.md at c902895, section 8)."""
    task = dataclasses.replace(task, world=dataclasses.replace(task.world, known_delay=seconds))
    if seconds >= task.world.dt / 2:
        local = dataclasses.replace(local, model_plans=0)
    return task, local


def detect_gravity(task: TaskConfig, enabled: bool) -> bool:
    """Whether the arm's commands lack gravity compensation, found from rollouts let go at the
    start pose (:func:`~lolgps_torch.arm_probes.measure_gravity`), said in one line when they do or
    when the probe cannot tell (then they are taken as compensated); False when not
    ``enabled`` or when the task already compensates them."""
    if not gravity_probed(task, enabled):
        return False
    settings = GravityConfig()
    estimate = measure_gravity(task, settings)
    if not estimate.compensated:
        print(
            "the arm's commands are not compensated for gravity (it falls as the URDF's model "
            f"predicts, in {settings.rollouts} rollouts let go at the start pose): the learner "
            "adds the model's g(q) to every command (--compensate-gravity; --no-detect-gravity "
            "to learn without)"
        )
    elif not estimate.conclusive:
        print(
            "whether the arm's commands are compensated for gravity is unclear (residuals "
            f"{estimate.rss_none:.3g} without, {estimate.rss_compensated:.3g} with, N^2 m^2): "
            "taken as compensated (--compensate-gravity to add the URDF model's g(q))"
        )
    return not estimate.compensated


def compensate_gravity(task: TaskConfig) -> TaskConfig:
    """The task whose learner adds its own model's ``g(q)`` to every command
    (``WorldConfig.compensate_gravity``: the planned start, the model prior and the
    controllers then act over model-based compensation, as on a compensated arm)."""
    return dataclasses.replace(task, world=dataclasses.replace(task.world, compensate_gravity=True))
