"""Shared command-line plumbing: the arm/task flags every script takes, and one-line errors."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

import torch

from lolgps_torch.cost.l12 import CostConfig
from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import PegConfig
from lolgps_torch.robot.placement import PlacementConfig
from lolgps_torch.sim.world import WorldConfig
from lolgps_torch.task import TaskConfig


def add_task_arguments(parser: argparse.ArgumentParser, default_urdf: str | None = None) -> None:
    """Flags that pick the arm, its peg and its start pose."""
    group = parser.add_argument_group("arm")
    group.add_argument(
        "--urdf", required=default_urdf is None, default=default_urdf, help="the arm's URDF file"
    )
    group.add_argument(
        "--ee-link",
        default=None,
        help="end-effector link (default: end of the longest actuated chain, "
        "or 'peg_tip' when the URDF carries its own peg)",
    )
    peg = PegConfig()
    group.add_argument(
        "--peg-length",
        type=float,
        default=peg.length,
        help="length (m) of the peg attached to arms without one",
    )
    group.add_argument(
        "--peg-radius", type=float, default=peg.radius, help="radius (m) of the attached peg"
    )
    group.add_argument(
        "--peg-axis",
        default=peg.axis,
        help="end-effector link axis the attached peg points along (x, y, z, -x, ...)",
    )
    group.add_argument(
        "--q0",
        type=float,
        nargs="+",
        default=None,
        help="start pose (rad); default: derived by inverse kinematics",
    )
    group.add_argument(
        "--friction",
        type=float,
        default=WorldConfig().friction,
        help="lateral friction of the table and the hole (the original GPS example: "
        "frictionless) (default %(default)s)",
    )
    cost = CostConfig()
    group.add_argument(
        "--action-weight",
        type=float,
        default=cost.action_weight,
        help="torque cost wu_j = action_weight / effort_j^2 (default %(default)s)",
    )
    group.add_argument(
        "--descent-height",
        type=float,
        default=cost.descent_height,
        help="lift the cost's targets by this height (m) at t = 0, falling linearly to the "
        "hole floor at --descent-steps, so the peg aligns over the hole before it goes down; "
        "0 turns it off (default %(default)s)",
    )
    group.add_argument(
        "--descent-steps",
        type=int,
        default=cost.descent_steps,
        help="step at which the lifted targets reach the hole floor; 0 turns it off "
        "(default %(default)s)",
    )


def task_config(args: argparse.Namespace) -> TaskConfig:
    """The :class:`TaskConfig` the arm flags describe."""
    peg = PegConfig(length=args.peg_length, radius=args.peg_radius, axis=args.peg_axis)
    placement = PlacementConfig(q0=tuple(args.q0) if args.q0 else None)
    if args.descent_height < 0.0 or args.descent_steps < 0:
        raise LolgpsError("--descent-height and --descent-steps must be >= 0")
    cost = CostConfig(
        action_weight=args.action_weight,
        descent_height=args.descent_height,
        descent_steps=args.descent_steps,
    )
    if args.friction < 0.0:
        raise LolgpsError(f"--friction {args.friction}: must be >= 0")
    world = WorldConfig(friction=args.friction)
    return TaskConfig(
        urdf=args.urdf, ee_link=args.ee_link, peg=peg, world=world, placement=placement, cost=cost
    )


def run(main: Callable[[], None]) -> None:
    """Run a script's main: a :class:`LolgpsError` becomes one ``error:`` line and exit 2.

    Torch runs on one intra-op thread (``LOLGPS_THREADS`` overrides): the tensors here are
    small, and a second thread only contends with the simulator and with parallel workers.
    """
    torch.set_num_threads(int(os.environ.get("LOLGPS_THREADS", "1")))
    try:
        main()
    except LolgpsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except BrokenPipeError:  # output piped into a reader that stopped (e.g. head)
        sys.stderr.close()
        sys.exit(1)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
