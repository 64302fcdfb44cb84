"""Film a run's noiseless rollouts at its training positions.

    lolgps render --run DIR [--conditions all|0,3,...] [--who policy|controller|both]
                  [--out FILE.mp4|FILE.gif] [--size W H] [--fps F] [--every K]
                  [--view wide|mouth] [--layout grid|sequence] [--columns N]
                  [--after C]

The final global policy (or the one checkpointed after condition C), and/or each condition's
final local controller, runs once without noise at each chosen training position; PyBullet's
CPU renderer then draws every K-th state from a fixed camera (wide: the hole and the peg's
start; mouth: a close-up of the funnel, cut open on the camera's side). Each clip is
captioned with its condition, hole offset, time, the tip's distance and its outcome (success
or miss at its final distance); clips go side by side in a grid or one after another. Writes
FILE (default DIR/videos/WHO-VIEW.mp4; an .mp4 needs the ``video`` extra, a .gif only
Pillow) and prints each clip's final distance. The rollouts run on the run's own plant; the
plant flags (``--payload``, ``--action-delay``, ...) change it, each one left out keeping the
run's. With ``--arm franka --robot-ip IP`` the rollouts run on the arm and the video replays
their joint angles (docs/REAL_ARM.md).

The same command: ``python scripts/render.py``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from lolgps_torch.cli import (
    ConfigFlags,
    add_arm_arguments,
    add_plant_arguments,
    arm_config,
    plant_config,
)
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.render import (
    RenderConfig,
    check_output,
    frame_count,
    parse_conditions,
    render_run,
)
from lolgps_torch.lolgps.run import load_run

FLAGS = ConfigFlags(RenderConfig())


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Film the run the command line ``argv`` (default: this process's) names."""
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    parser.add_argument(
        "--conditions", default="all", help="'all' (default) or condition indices: 0,3,5"
    )
    parser.add_argument(
        "--after",
        type=int,
        default=None,
        help="film the policy checkpointed after this condition (default: the last)",
    )
    parser.add_argument("--out", default=None, help="the video (default DIR/videos/WHO-VIEW.mp4)")
    FLAGS.add_to(parser)
    add_plant_arguments(parser)
    add_arm_arguments(parser)
    args = parser.parse_args(argv)
    real = arm_config(args)
    config: RenderConfig = FLAGS.build(args)
    out = check_output(args.out or Path(args.run) / "videos" / f"{config.who}-{config.view}.mp4")
    loaded = load_run(args.run)
    task = replace(loaded.info.task, plant=plant_config(args, loaded.info.task.plant))
    loaded = replace(loaded, info=replace(loaded.info, task=task))
    completed = [r.condition for r in loaded.records]
    conditions = parse_conditions(args.conditions, completed)
    if args.after is not None and args.after not in completed:
        raise LolgpsError(f"--after {args.after}: not a completed condition ({completed})")
    start = time.perf_counter()
    clips = render_run(loaded, conditions, config, out, args.after, real)
    seconds = time.perf_counter() - start
    threshold = loaded.info.task.world.success_threshold
    print(f"{'who':<10} {'condition':>9} {'offset (mm)':>16} {'final (mm)':>10}  outcome")
    for clip in clips:
        dx, dy = (1000 * v for v in clip.offset)
        outcome = "success" if clip.success else "miss"
        print(
            f"{clip.who:<10} {clip.condition:>9d} {dx:+7.1f} {dy:+7.1f} "
            f"{1000 * clip.final_distance:>10.1f}  {outcome}"
        )
    n = frame_count(len(clips), len(clips[0].q) - 1, config)
    print(f"success = final distance < {threshold * 1000:.0f} mm")
    print(f"wrote {out} ({n} frames at {config.fps:g} fps) in {seconds:.1f} s")
