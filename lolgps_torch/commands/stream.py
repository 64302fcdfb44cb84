"""A stream run from its configs, the one call under ``lolgps run``, scripts/run_stream.py
and a sweep's cells: :func:`run_stream` plans the run (:func:`plan_stream`: the stream's
conditions, the output folder checked, the geometry scaled and placed, the arm probed for
gravity compensation and command delay, or all of it as the folder records on resume), writes
config.json and arm.urdf, runs the learner with a line per record and writes summary.json."""

from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

import torch

from lolgps_torch.arm_probes import fit_scale, scaled
from lolgps_torch.cli import check_device
from lolgps_torch.commands.lines import condition_line, print_table, record_line
from lolgps_torch.commands.probes import (
    allow_for_delay,
    compensate_gravity,
    detect_delay,
    detect_gravity,
    start_rollouts,
)
from lolgps_torch.data.records import (
    ConditionSummary,
    DistillRecord,
    IdentifiedRecord,
    IterationRecord,
)
from lolgps_torch.data.run_folder import (
    RunFolder,
    arm_urdf,
    as_stored,
    config_differences,
    task_json,
)
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.evaluation.square import SquareConfig, square_stream
from lolgps_torch.lolgps import StreamConfig, make_learner, method_config
from lolgps_torch.lolgps.run import Position
from lolgps_torch.progress import Bar
from lolgps_torch.robot.placement import pinned
from lolgps_torch.sim.franka import SIMULATED, RealArmConfig
from lolgps_torch.task import PegTask, TaskConfig


@dataclass(frozen=True)
class StreamSettings:
    """What a stream run is made from (``lolgps run``'s flags, checked).

    :param task: the arm, its peg and start pose, the world, the cost and the plant.
    :param stream: the learner's settings; its seed also draws the paper's and the square's
        positions.
    :param method: ``lolgps``, ``naive`` or ``batch`` (:func:`method_config` sets what it
        implies).
    :param conditions: the hole offsets (m) to learn, in order; None: the ``kind`` stream's.
    :param kind: ``paper`` (train0 to train2) or ``square`` (``count`` positions).
    :param count: the square stream's positions.
    :param scale: the factor in (0, 1] the geometry is scaled by; None: by the arm's reach,
        only where the default geometry does not fit.
    :param out: the run folder (None: ``runs/<method>-seed<S>``).
    :param resume: continue the run ``out`` holds.
    :param device: the torch device the learner runs on.
    :param workers: the processes a batch of rollouts is spread over.
    :param detect_gravity: probe whether the arm's commands are compensated for gravity.
    :param detect_delay: estimate the arm's command delay.
    :param real: the real arm the rollouts run on (none: the simulator).
    """

    task: TaskConfig
    stream: StreamConfig = StreamConfig()
    method: str = "lolgps"
    conditions: tuple[Position, ...] | None = None
    kind: Literal["paper", "square"] = "paper"
    count: int = SquareConfig().count
    scale: float | None = None
    out: str | None = None
    resume: bool = False
    device: str = "cpu"
    workers: int = 1
    detect_gravity: bool = True
    detect_delay: bool = True
    real: RealArmConfig = SIMULATED


@dataclass(frozen=True)
class Plan:
    """A run, checked, before anything is written.

    :param config: config.json's content. :param urdf_text: the arm's URDF copy.
    :param task: the task to build (from the folder's copy on resume).
    """

    folder: RunFolder
    config: dict[str, Any]
    urdf_text: str
    method: str
    stream: StreamConfig
    task: TaskConfig
    conditions: list[Position]
    device: torch.device


def check_folder(folder: RunFolder, config: dict[str, Any], resume: bool) -> None:
    """A new run needs a writable folder without a run; a resumed one a folder whose run has
    this configuration (the differing fields are named)."""
    if resume:
        if not folder.has_config():
            raise LolgpsError(f"--resume: {folder.path} holds no run to continue")
        differences = config_differences(folder.read_config(), config)
        if differences:
            raise LolgpsError(
                f"{folder.path} holds a run with another configuration: " + "; ".join(differences)
            )
    elif folder.has_config():
        raise LolgpsError(
            f"{folder.path} already holds a run; pass --resume to continue it, or another --out"
        )
    folder.check_writable()


# config.json's and summary.json's note of a gravity compensation found missing
GRAVITY_NOTE = "detected_gravity_compensation"
DELAY_NOTE = "detected_delay"  # and of the command delay (s) found
START_NOTE = "start_rollouts"  # config.json's count of the probes' rollouts before the stream


def stream_conditions(settings: StreamSettings) -> tuple[list[Position], list[dict[str, Any]]]:
    """The stream's hole offsets and its stages (``{"name", "last_condition"}``)."""
    if settings.conditions is not None:
        conditions = list(settings.conditions)
        return conditions, [{"name": "stream", "last_condition": len(conditions) - 1}]
    if settings.kind == "square":
        return square_stream(SquareConfig(count=settings.count), settings.stream.seed)
    return default_training_stream(AreaConfig(), settings.stream.seed)


@dataclass(frozen=True)
class SetUp:
    """A stream as it is learnt: its task (scaled, placed, allowing for what the probes found),
    the learner's settings (the method's, and the delay's), its conditions and stages, and
    config.json's notes of the probes."""

    task: TaskConfig
    stream: StreamConfig
    conditions: list[Position]
    stages: list[dict[str, Any]]
    notes: dict[str, Any]


def placed_task(
    settings: StreamSettings, task: TaskConfig, resumed: RunFolder | None
) -> TaskConfig:
    """``task`` scaled and placed as the run in ``resumed`` was, else scaled by
    ``settings.scale`` or to fit the arm (saying so)."""
    if resumed is not None:  # the scale, hole and start pose it was placed at
        saved = resumed.task_config(resumed.read_config()["task"])
        task = scaled(task, saved.scale)
        placement = replace(task.placement, mouth=saved.placement.mouth, q0=saved.placement.q0)
        return replace(task, placement=placement)
    if settings.scale is not None:
        return scaled(task, settings.scale)
    task, note = fit_scale(task)
    if note:
        print(note)
    return task


def probed(
    settings: StreamSettings, task: TaskConfig, stream: StreamConfig, resumed: RunFolder | None
) -> tuple[TaskConfig, StreamConfig, dict[str, Any]]:
    """The task and stream allowing for what the probes find on the simulated arm (gravity
    first: it steadies the delay's excitation), and config.json's notes of it; as the run in
    ``resumed`` records, if given."""
    simulated = settings.real.arm == "simulated"
    gravity, delay = settings.detect_gravity and simulated, settings.detect_delay and simulated
    recorded = {} if resumed is None else resumed.read_config()
    start: int | None
    if resumed is None:
        start, uncompensated = start_rollouts(task, gravity, delay), detect_gravity(task, gravity)
    else:
        start, uncompensated = recorded.get(START_NOTE), recorded.get(GRAVITY_NOTE) == "none"
    notes: dict[str, Any] = {} if start is None else {START_NOTE: start}
    if uncompensated:
        task = compensate_gravity(task)
        notes[GRAVITY_NOTE] = "none"
    seconds = detect_delay(task, delay) if resumed is None else float(recorded.get(DELAY_NOTE, 0.0))
    if seconds > 0.0:
        task, local = allow_for_delay(task, stream.local, seconds)
        stream = replace(stream, local=local)
        notes[DELAY_NOTE] = seconds
    return task, stream, notes


def set_up(settings: StreamSettings, resumed: RunFolder | None = None) -> SetUp:
    """The stream ``settings`` describe as it is learnt (the probes run on the arm), or as the
    run in ``resumed`` set it up; nothing written."""
    stream = method_config(settings.method, settings.stream)
    conditions, stages = stream_conditions(settings)
    task = replace(
        settings.task, placement=replace(settings.task.placement, positions=tuple(conditions))
    )
    task = placed_task(settings, task, resumed)
    task, stream, notes = probed(settings, task, stream, resumed)
    return SetUp(task, stream, list(task.placement.positions), stages, notes)


def plan_stream(settings: StreamSettings) -> Plan:
    """Check the settings, the output folder (before the placement's search, which may take a
    while) and the conditions, and set the stream up (:func:`set_up`); write nothing."""
    device = check_device(settings.device)
    seed = settings.stream.seed
    folder = RunFolder(settings.out or os.path.join("runs", f"{settings.method}-seed{seed}"))
    resumed = folder if settings.resume and folder.has_config() else None
    if resumed is None:
        check_folder(folder, {}, settings.resume)
    setup = set_up(settings, resumed)
    urdf_text = arm_urdf(setup.task)
    config = as_stored(
        {
            "method": settings.method,
            "seed": seed,
            "task": task_json(setup.task, urdf_text),
            "stream": asdict(setup.stream),
            "conditions": [list(c) for c in setup.conditions],
            "stages": setup.stages,
            **setup.notes,
        }
    )
    task = setup.task
    if settings.resume:
        check_folder(folder, config, settings.resume)
        task = folder.task_config(config["task"])
    return Plan(
        folder, config, urdf_text, settings.method, setup.stream, task, setup.conditions, device
    )


def learn(plan: Plan, task: PegTask, started: float) -> list[ConditionSummary]:
    """Run the plan's learner in its folder, logging every record to metrics.jsonl and the
    terminal (with a bar over the conditions on a terminal); write summary.json at the end,
    and the wall time since ``started`` (``time.perf_counter``) as metrics.jsonl's last line
    (summary.json holds only what the seed decides)."""
    folder, total = plan.folder, len(plan.conditions)
    bar = Bar(total, "conditions")

    def log(record: IterationRecord | IdentifiedRecord | DistillRecord) -> None:
        folder.append_metrics(record.to_json())
        bar.write(record_line(record, total))

    def done(entry: ConditionSummary) -> None:
        bar.write(condition_line(entry, total))
        bar.update()

    learner = make_learner(plan.method, task, plan.stream, folder, log)
    try:
        summary = learner.run(plan.conditions, done)
    finally:
        bar.close()
    folder.append_metrics({"event": "finished", "seconds": time.perf_counter() - started})
    detected = {k: v for k, v in plan.config.items() if k in (GRAVITY_NOTE, DELAY_NOTE)}
    folder.write_summary(
        {
            "method": plan.method,
            "seed": plan.config["seed"],
            **detected,
            "arm_rollouts": arm_rollouts(summary, int(plan.config.get(START_NOTE) or 0)),
            **arm_use(summary),
            "conditions": [e.to_json() for e in summary],
        }
    )
    return summary


def arm_rollouts(summary: list[ConditionSummary], start: int) -> dict[str, int]:
    """The stream's rollouts on the arm by kind: ``start`` (the probes before the stream), the
    conditions' samples, probes and visits, and the final policy's check at every condition
    (a probe each), with their ``total``."""
    kinds = {"start": start}
    for entry in summary:
        for kind, count in entry.arm_rollouts.items():
            kinds[kind] = kinds.get(kind, 0) + count
    if any(entry.arm_rollouts for entry in summary):  # the final check, where counted
        kinds["probe"] = kinds.get("probe", 0) + len(summary)
    return {**kinds, "total": sum(kinds.values())}


def arm_use(summary: list[ConditionSummary]) -> dict[str, Any]:
    """Summed over the conditions: the rollouts stopped at a limit by kind (``arm_faults``,
    with their ``total``), the rollouts on the arm's model instead (``model_rollouts``, and
    ``model_faults`` those stopped), and on a real arm its seconds (``arm_seconds``)."""
    faults: Counter[str] = Counter()
    for entry in summary:
        faults.update(entry.arm_faults)
    use: dict[str, Any] = {
        "arm_faults": {**faults, "total": sum(faults.values())},
        "model_rollouts": sum(entry.model_rollouts for entry in summary),
        "model_faults": sum(entry.model_faults for entry in summary),
    }
    seconds = [entry.arm_seconds for entry in summary if entry.arm_seconds is not None]
    if seconds:
        use["arm_seconds"] = sum(seconds)
    return use


def run_stream(settings: StreamSettings, started: float | None = None) -> list[ConditionSummary]:
    """Plan the run (:func:`plan_stream`), start its folder (or continue it on resume), learn
    the stream and print its table; return the conditions' summaries. ``started``
    (``time.perf_counter``, default now) starts the wall time metrics.jsonl ends with."""
    started = time.perf_counter() if started is None else started
    plan = plan_stream(settings)
    local = plan.stream.local
    task = PegTask(plan.task, local.samples, str(plan.device), settings.workers, settings.real)
    try:  # the task's placement has checked every condition's reachability
        if not settings.resume:  # recorded with the hole and start pose it was placed at
            placed = replace(plan.task, placement=pinned(plan.task.placement, task.geometry))
            config = {**plan.config, "task": task_json(placed, plan.urdf_text)}
            plan.folder.start(config, plan.urdf_text)
        summary = learn(plan, task, started)
    finally:
        task.close()
    print_table(summary, plan.folder)
    return summary
