"""Learn a stream of conditions with LOLGPS (paper Algorithm 2): the project's main command.

    python scripts/run_stream.py --urdf robots/kuka_peg.urdf

With no other flags it runs the paper's training stream in the default geometry: train0 = the
4 hole offsets (+-0.02, +-0.02) m around the nominal position, train1 = +2 seeded positions in
test area 2 (0.10 m along the table's lateral axis), train2 = +2 in area 4 (0.20 m).

It writes into --out: config.json, arm.urdf (the arm's URDF, so the folder stands alone),
metrics.jsonl (one line per iteration, with phase times), replay.h5 (the successful
trajectories D_g of every condition), checkpoints/after_condition_XXX/ (the global policy after
each condition) and summary.json, and prints a table at the end. Every flag, the output folder
and the reachability of every hole offset (the hole is placed so that all are reachable)
are checked before anything is written. An
interrupted run continues from its last completed condition with --resume.

Unless --compensate-gravity is given or --no-detect-gravity, the arm is first let go at the
start pose for a few control steps (``lolgps_torch/sim/gravity.py``): where it falls as the
URDF's model predicts without gravity compensation, the learner adds the model's g(q) to every
command (config.json's ``task.world.compensate_gravity``), as one printed line, config.json's
and summary.json's ``detected_gravity_compensation`` ("none") say.

Unless --known-delay is given or --no-detect-delay, the arm's command delay is first estimated
from a few excitation rollouts at the start pose (``lolgps_torch/sim/latency.py``, on
random streams of its own); a delay found (not zero) becomes the learner's known delay, and
from half a control step on the first controller is the hold (``--model-plans 0``), as one
printed line, config.json's and summary.json's ``detected_delay`` (s) say.

With ``--arm franka --robot-ip IP`` the rollouts run on a Franka, one at a time, neither
detection runs, and each rollout is reported in one line (docs/REAL_ARM.md).
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import torch

from lolgps_torch.arm_probes import fit_scale, scaled
from lolgps_torch.cli import (
    ConfigFlags,
    Position,
    add_arm_arguments,
    add_delay_argument,
    add_gravity_argument,
    add_task_arguments,
    add_workers_argument,
    allow_for_delay,
    arm_config,
    check_device,
    compensate_gravity,
    detect_delay,
    detect_gravity,
    read_offsets,
    run,
    scale_factor,
    start_rollouts,
    task_config,
    workers,
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
from lolgps_torch.lolgps import METHODS, StreamConfig, make_learner, method_config
from lolgps_torch.progress import Bar
from lolgps_torch.robot.placement import pinned
from lolgps_torch.task import PegTask, TaskConfig

STREAM_FLAGS = ConfigFlags(
    StreamConfig(),
    renames={
        "samples": ("local.samples",),
        "distill-steps": ("policy.steps",),
        "distill-batch": ("policy.batch_size",),
        "pre-weight": ("policy.pre_weight",),
        "adam-dtype": ("policy.adam_dtype",),
        "no-guard": ("policy.guard",),
        "guard-torque": ("policy.guard_torque",),
        "guard-speed": ("policy.guard_speed",),
        "guard-window": ("policy.guard_window",),
        "guard-retreat": ("policy.guard_retreat",),
        "guard-brake": ("policy.guard_brake",),
        "guard-hover": ("policy.guard_hover",),
        "guard-hover-time": ("policy.guard_hover_time",),
        "guard-limit": ("policy.guard_limit",),
        "no-replay": ("replay",),
        "seed": ("seed", "policy.seed"),
        "dynamics-prior": ("local.dynamics.prior",),
        "model-plans": ("local.model_plans",),
        "identify": ("local.identify",),
    },
    skip=("use_pre",),  # set by --method
)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser, default_urdf="robots/kuka_peg.urdf")
    parser.add_argument(
        "--scale",
        default="auto",
        help="scale the stream's geometry (hole offsets, test areas, start height, attached "
        "peg) by FACTOR in (0, 1]; auto: by the arm's reach, only where the default geometry "
        "does not fit (default auto)",
    )
    parser.add_argument(
        "--stream",
        choices=("paper", "square"),
        default="paper",
        help="paper: train0 (4 corners), train1 (+2 in area 2), train2 (+2 in area 4); square: "
        "--count positions uniform in a 0.20 m square about the nominal hole, from --seed "
        "(default %(default)s)",
    )
    parser.add_argument(
        "--count",
        type=int,
        default=SquareConfig().count,
        help="positions of the square stream (default %(default)s)",
    )
    parser.add_argument(
        "--conditions",
        default=None,
        help="JSON file with a list of planar hole offsets [[dx, dy], ...] (m), instead of "
        "--stream",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default="lolgps",
        help="lolgps; naive sequential (no p_pre, no replay, alpha 0); or batch GPS (all "
        "conditions at once, an S-step every iteration; --resume restarts it) "
        "(default: lolgps)",
    )
    STREAM_FLAGS.add_to(parser.add_argument_group("stream"))
    parser.add_argument(
        "--out", default=None, help="output folder (default: runs/<method>-seed<S>)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="continue an interrupted run in --out"
    )
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    add_gravity_argument(parser)
    add_delay_argument(parser)
    add_workers_argument(parser)
    add_arm_arguments(parser)
    return parser.parse_args(argv)


@dataclass(frozen=True)
class Plan:
    """A run, checked, before anything is written.

    :param config: config.json's content. :param urdf_text: the arm's URDF copy.
    :param task: the task to build (from the folder's copy on --resume).
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
    """A new run needs a writable folder without a run; --resume one whose run has this
    configuration (the differing fields are named)."""
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
START_NOTE = "start_rollouts"  # config.json's count of the probes' rollouts before the stream


def detected_gravity(args: argparse.Namespace, task: TaskConfig, folder: RunFolder) -> bool:
    """Whether the run compensates gravity for the arm beyond the flags: on --resume as its
    folder records, else as :func:`~lolgps_torch.cli.detect_gravity` finds."""
    if args.resume:
        return folder.read_config().get(GRAVITY_NOTE) == "none"
    return detect_gravity(task, args.detect_gravity and args.arm == "simulated")


def detected_delay(args: argparse.Namespace, task: TaskConfig, folder: RunFolder) -> float:
    """The command delay (s) the run allows for beyond the flags: on --resume the one its
    folder records, else the one :func:`~lolgps_torch.cli.detect_delay` estimates."""
    if args.resume:
        return float(folder.read_config().get("detected_delay", 0.0))
    return detect_delay(task, args.detect_delay and args.arm == "simulated")


def plan_run(args: argparse.Namespace) -> Plan:
    """Check every flag, the conditions and the output folder; write nothing."""
    device = check_device(args.device)
    stream = method_config(args.method, STREAM_FLAGS.build(args))
    task = task_config(args)
    if args.conditions is not None:
        conditions = read_offsets(args.conditions, "--conditions")
        stages = [{"name": "stream", "last_condition": len(conditions) - 1}]
    elif args.stream == "square":
        conditions, stages = square_stream(SquareConfig(count=args.count), args.seed)
    else:
        conditions, stages = default_training_stream(AreaConfig(), args.seed)
    task = replace(task, placement=replace(task.placement, positions=tuple(conditions)))
    folder = RunFolder(args.out or os.path.join("runs", f"{args.method}-seed{args.seed}"))
    if args.resume and folder.has_config():  # the scale, hole and start pose it was placed at
        saved = folder.task_config(folder.read_config()["task"])
        task = scaled(task, saved.scale)
        task = replace(
            task,
            placement=replace(task.placement, mouth=saved.placement.mouth, q0=saved.placement.q0),
        )
    else:  # the folder checked before the placement's search, which may take a while
        check_folder(folder, {}, args.resume)
        if args.scale != "auto":
            task = scaled(task, scale_factor(args.scale))
        else:
            task, note = fit_scale(task)
            if note:
                print(note)
    conditions = list(task.placement.positions)
    urdf_text = arm_urdf(task)
    noted: dict[str, Any] = {}
    simulated = args.arm == "simulated"
    start = (  # the rollouts the probes below take on the arm (as recorded, on --resume)
        folder.read_config().get(START_NOTE)
        if args.resume
        else start_rollouts(
            task, args.detect_gravity and simulated, args.detect_delay and simulated
        )
    )
    if start is not None:
        noted[START_NOTE] = start
    if detected_gravity(args, task, folder):  # before the delay's excitation, which it steadies
        task = compensate_gravity(task)
        noted[GRAVITY_NOTE] = "none"
    delay = detected_delay(args, task, folder)
    if delay > 0.0:
        task, local = allow_for_delay(task, stream.local, delay)
        stream = replace(stream, local=local)
        noted["detected_delay"] = delay
    config = as_stored(
        {
            "method": args.method,
            "seed": args.seed,
            "task": task_json(task, urdf_text),
            "stream": asdict(stream),
            "conditions": [list(c) for c in conditions],
            "stages": stages,
            **noted,
        }
    )
    if args.resume:
        check_folder(folder, config, args.resume)
        task = folder.task_config(config["task"])
    return Plan(folder, config, urdf_text, args.method, stream, task, conditions, device)


def _record_line(record: IterationRecord | IdentifiedRecord | DistillRecord, total: int) -> str:
    if isinstance(record, DistillRecord):
        return f"S-step took {record.time_distill:.1f}s"
    if isinstance(record, IdentifiedRecord):
        return (
            f"condition {record.condition + 1}/{total}  arm identified: payload "
            f"{record.payload:.3f} kg, gravity compensation x {record.compensation:.3f} "
            f"(its own gravity's share {record.own_compensation:.2f}); one-step "
            f"joint-speed error on its first rollouts {record.error_identified:.4f} rad/s "
            f"(URDF model {record.error_urdf:.4f}, the simulated arm's own "
            f"{record.error_plant:.4f}; {record.transitions} free transitions)"
        )
    return (
        f"condition {record.condition + 1}/{total}  iter {record.iteration:2d}  "
        f"cost {record.mean_cost:8.2f}  distance mean {record.mean_distance:.3f} "
        f"best {record.best_distance:.3f}  success {record.success_rate:4.0%}  "
        f"faults {record.faults}  "
        f"[{record.time_sample:.2f}s sample, {record.time_fit:.2f}s fit, "
        f"{record.time_cstep:.2f}s C-step]"
    )


def _condition_line(entry: ConditionSummary, total: int) -> str:
    failure = f"; failed: {entry.failure}" if entry.failure else ""
    kinds = ", ".join(f"{n} {kind}s" for kind, n in entry.arm_rollouts.items())
    return (
        f"condition {entry.condition + 1}/{total} done: first success at iteration "
        f"{entry.first_success_iteration}, p_cur distance {entry.local_final_distance:.4f}, "
        f"global policy distance {entry.policy_final_distance_after:.4f}, faults "
        f"{entry.faults}; arm rollouts {sum(entry.arm_rollouts.values())} ({kinds}){failure}"
    )


def _print_table(summary: list[ConditionSummary], folder: RunFolder) -> None:
    print(
        f"\n{'cond':>4} {'offset (m)':>17} {'iters':>5} {'1st ok':>6} {'p_cur':>8} "
        f"{'pi after':>9} {'pi end':>8}"
    )
    for e in summary:
        first = "-" if e.first_success_iteration is None else str(e.first_success_iteration)
        print(
            f"{e.condition:>4} ({e.offset[0]:+.3f}, {e.offset[1]:+.3f}) {e.iterations:>5} "
            f"{first:>6} {e.local_final_distance:8.4f} {e.policy_final_distance_after:9.4f} "
            f"{e.policy_final_distance_end:8.4f}"
        )
    solved = sum(bool(e.policy_success_end) for e in summary)
    print(
        f"global policy alone succeeds at {solved}/{len(summary)} training positions; "
        f"results in {folder.path}"
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
        bar.write(_record_line(record, total))

    def done(entry: ConditionSummary) -> None:
        bar.write(_condition_line(entry, total))
        bar.update()

    learner = make_learner(plan.method, task, plan.stream, folder, log)
    try:
        summary = learner.run(plan.conditions, done)
    finally:
        bar.close()
    folder.append_metrics({"event": "finished", "seconds": time.perf_counter() - started})
    detected = {k: v for k, v in plan.config.items() if k in (GRAVITY_NOTE, "detected_delay")}
    folder.write_summary(
        {
            "method": plan.method,
            "seed": plan.config["seed"],
            **detected,
            "arm_rollouts": arm_rollouts(summary, int(plan.config.get(START_NOTE) or 0)),
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


def main() -> None:
    started = time.perf_counter()
    args = parse_args()
    processes = workers(args)  # checked before the placement's search
    real = arm_config(args)
    plan = plan_run(args)
    task = PegTask(plan.task, plan.stream.local.samples, str(plan.device), processes, real)
    try:  # the task's placement has checked every condition's reachability
        if not args.resume:  # recorded with the hole and start pose it was placed at
            placed = replace(plan.task, placement=pinned(plan.task.placement, task.geometry))
            config = {**plan.config, "task": task_json(placed, plan.urdf_text)}
            plan.folder.start(config, plan.urdf_text)
        summary = learn(plan, task, started)
    finally:
        task.close()
    _print_table(summary, plan.folder)


if __name__ == "__main__":
    run(main)
