"""Evaluate a run's global policies on the test areas (paper Figs. 3-4).

    lolgps evaluate --run DIR [--workers 2] [--positions FILE] [--areas N]
                    [--per-area P] [--area-seed S] [--scratch DIR]
                    [--ray [ADDRESS]]

For each training stage, the policy checkpointed after its last condition runs without noise
at every test position (default: 7 areas of 50 positions, docs/ALGORITHM.md section 9). Writes
DIR/eval.json (per stage and area: mean final distance, mean total cost and success rate with
95% CIs; forgetting, average final success, forward transfer) and DIR/fig4.png, and prints a
table. ``--positions FILE`` (a JSON list of [dx, dy] in metres) evaluates those positions
instead of the areas; ``--scratch DIR`` takes from-scratch iterations to first success from
another run's summary.json for forward transfer. ``--ray`` runs the rollouts on Ray actors (a
local instance, or the cluster at ADDRESS) instead of processes, with the same results.
The rollouts run on the run's own plant (config.json's ``task.plant``); the plant flags
(``--payload``, ``--action-delay``, ...) change it, each one left out keeping the run's.
They run in the run's own simulator (``task.sim``) unless ``--sim`` names another: a policy
learnt in one simulator tested in the other. With ``--arm franka --robot-ip IP`` they run on
the arm, one at a time (docs/REAL_ARM.md).

The same command: ``python scripts/evaluate.py``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import replace
from typing import get_args

from lolgps_torch.cli import (
    add_arm_arguments,
    add_plant_arguments,
    arm_config,
    plant_config,
    read_offsets,
)
from lolgps_torch.cluster import import_ray
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig
from lolgps_torch.evaluation.evaluate import evaluate_run
from lolgps_torch.evaluation.plot import plot_fig4
from lolgps_torch.evaluation.square import SquareConfig
from lolgps_torch.evaluation.table import format_table
from lolgps_torch.lolgps.run import read_run
from lolgps_torch.sim.simulator import Simulator


def make_parser(defaults: AreaConfig, prog: str | None = None) -> argparse.ArgumentParser:
    """The flags, with the area defaults of ``defaults`` in their help, and ``prog`` as the
    command's name in the usage (default: the script's)."""
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (with config.json, checkpoints/)")
    parser.add_argument("--workers", type=int, default=2, help="rollout processes (default 2)")
    parser.add_argument("--positions", default=None, help="JSON list of [dx, dy] to evaluate")
    parser.add_argument(
        "--square",
        action="store_true",
        help="the square stream's test set: 200 positions uniform in the 0.20 m square, from "
        "--area-seed, none of them a training position (instead of the areas)",
    )
    parser.add_argument(
        "--areas", type=int, default=None, help=f"number of test areas (default {defaults.n_areas})"
    )
    parser.add_argument(
        "--per-area",
        type=int,
        default=None,
        help=f"test positions per area (default {defaults.positions_per_area})",
    )
    parser.add_argument(
        "--area-seed",
        type=int,
        default=None,
        help=f"seed of the test positions (default {defaults.seed})",
    )
    parser.add_argument(
        "--scratch",
        default=None,
        help="from-scratch baselines for forward transfer: 'auto' learns every training "
        "condition alone for 10 iterations in the worker processes (cached in the run's "
        "scratch.json), or a run folder with the same conditions (e.g. a naive run)",
    )
    parser.add_argument(
        "--batch-size",
        type=int,
        default=10,
        help="rollouts stepped together per worker (default 10)",
    )
    parser.add_argument(
        "--ray",
        nargs="?",
        const="local",
        default=None,
        metavar="ADDRESS",
        help="roll out on Ray actors instead of processes: alone, a local instance of --workers "
        "CPUs; with an address (e.g. auto), that cluster (needs pip install -e '.[ray]')",
    )
    parser.add_argument(
        "--sim",
        choices=get_args(Simulator),
        default=None,
        help="the simulator the rollouts run in (default: the run's)",
    )
    add_plant_arguments(parser)
    add_arm_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Evaluate the run the command line ``argv`` (default: this process's) names."""
    defaults = AreaConfig()
    args = make_parser(defaults, prog).parse_args(argv)
    if args.workers < 1:
        raise LolgpsError(f"--workers {args.workers}: must be at least 1")
    real = arm_config(args)
    if args.ray is not None and real.arm != "simulated":
        raise LolgpsError(f"--ray runs rollouts on Ray actors, --arm {real.arm} on the arm")
    if args.ray is not None:
        import_ray()
    areas, positions, square = test_set(args, defaults)
    plant = plant_config(args, read_run(RunFolder(args.run)).task.plant)
    evaluation = evaluate_run(
        args.run,
        args.workers,
        areas=areas,
        positions=positions,
        scratch=args.scratch,
        batch_size=args.batch_size,
        square=square,
        ray=args.ray,
        plant=plant,
        sim=args.sim,
        real=real,
    )
    folder = RunFolder(args.run)
    plot_fig4(evaluation, folder.figure_path)
    print(format_table(evaluation))
    print(f"wrote {folder.eval_path} and {folder.figure_path}")


def test_set(
    args: argparse.Namespace, defaults: AreaConfig
) -> tuple[AreaConfig | None, list[tuple[float, float]] | None, tuple[SquareConfig, int] | None]:
    """The test areas, the explicit positions or the square's test set the flags choose."""
    area_flags = {
        "n_areas": args.areas,
        "positions_per_area": args.per_area,
        "seed": args.area_seed,
    }
    chosen = {name: value for name, value in area_flags.items() if value is not None}
    if args.positions is not None and chosen:
        raise LolgpsError(
            "--positions replaces the test areas: drop --areas/--per-area/--area-seed"
        )
    if args.square and (args.positions is not None or args.areas or args.per_area):
        raise LolgpsError("--square replaces the test areas and --positions")
    positions = read_offsets(args.positions, "--positions") if args.positions else None
    square = (SquareConfig(), args.area_seed or 0) if args.square else None
    areas = replace(defaults, **chosen) if positions is None and square is None else None
    return areas, positions, square
