"""Learn a stream of conditions with LOLGPS (paper Algorithm 2): the project's main command.

    lolgps run --urdf robots/kuka_peg.urdf
    python scripts/run_stream.py --urdf robots/kuka_peg.urdf      (the same)

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
import time
from collections.abc import Sequence

from lolgps_torch.cli import (
    DEFAULT_URDF,
    ConfigFlags,
    add_arm_arguments,
    add_delay_argument,
    add_gravity_argument,
    add_task_arguments,
    add_workers_argument,
    arm_config,
    read_offsets,
    scale_factor,
    task_config,
    workers,
)
from lolgps_torch.commands.stream import StreamSettings, run_stream
from lolgps_torch.evaluation.square import SquareConfig
from lolgps_torch.lolgps import METHODS, StreamConfig

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
        "guard-position": ("policy.guard_position",),
        "no-replay": ("replay",),
        "seed": ("seed", "policy.seed"),
        "dynamics-prior": ("local.dynamics.prior",),
        "model-plans": ("local.model_plans",),
        "identify": ("local.identify",),
    },
    skip=("use_pre",),  # set by --method
)


def build_parser(prog: str | None = None) -> argparse.ArgumentParser:
    """The command's flags, with ``prog`` as its name in the usage (default: the script's)."""
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser, default_urdf=DEFAULT_URDF)
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
    return parser


def stream_settings(args: argparse.Namespace) -> StreamSettings:
    """The :class:`StreamSettings` the parsed flags describe, every flag checked (the workers
    and the arm's first: they are checked before the placement's search)."""
    processes, real = workers(args), arm_config(args)
    stream: StreamConfig = STREAM_FLAGS.build(args)
    task = task_config(args)
    conditions = None
    if args.conditions is not None:
        conditions = tuple(read_offsets(args.conditions, "--conditions"))
    return StreamSettings(
        task=task,
        stream=stream,
        method=args.method,
        conditions=conditions,
        kind=args.stream,
        count=args.count,
        scale=None if args.scale == "auto" else scale_factor(args.scale),
        out=args.out,
        resume=args.resume,
        device=args.device,
        workers=processes,
        detect_gravity=args.detect_gravity,
        detect_delay=args.detect_delay,
        real=real,
    )


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Learn the stream the command line ``argv`` (default: this process's) describes."""
    started = time.perf_counter()
    run_stream(stream_settings(build_parser(prog).parse_args(argv)), started)
