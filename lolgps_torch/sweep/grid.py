"""Sweeps of ``lolgps run`` over a grid of seeds x methods x arms x streams (x variants),
on Ray, and their aggregate.

    lolgps sweep --seeds 0-2 --methods lolgps naive batch \\
        --urdf robots/kuka_peg.urdf --out runs/sweep1 [--conditions FILE] [--evaluate] \\
        [--address auto] [--num-cpus N] [--variants FILE] [-- extra run flags]

Each cell of the grid is one ``lolgps run`` in its own folder under ``--out``, named
``<method>-<urdf stem>-<stream>-seed<S>``. ``--variants`` names a JSON object of named
run flag sets, ``{"payload": "--payload 1", "gmm": "--dynamics-prior gmm"}``: every
cell then runs once per variant, with its flags after the common ones, in a folder named
``<method>-<urdf stem>-<stream>-<variant>-seed<S>``. Without --address a local Ray instance
with --num-cpus CPUs (default: all) runs the cells; --address auto joins a running cluster.
A Ray task (one CPU) runs the cell's commands in a Python process of their own
(``python -m lolgps_torch``): ``run`` (with ``--resume`` when the folder already holds
config.json), then, with ``--evaluate``, ``evaluate --workers 1``. A cell's run is thus a
command-line run, with its own process state, and its folder resumes the same way; no
PyBullet client crosses a process. The commands' output, the physics engine's included, goes
to the cell's ``sweep.log``, and the wall time of its attempts to ``sweep_cell.json``.

A failed cell is retried once and reported with its last ``error:`` line; the others carry
on. Rerunning the same command skips finished cells (summary.json, and eval.json with
``--evaluate``) and resumes interrupted ones. At the end ``--out`` holds ``sweep.json`` (the
grid and each cell's outcome) and the aggregate over seeds: ``summary.md``, ``summary.csv``
and ``summary.png``; the exit status is 1 if a cell finally failed. Needs Ray
(``pip install 'lolgps_torch[ray]'``). The same command: ``python scripts/sweep.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import socket
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

from lolgps_torch.cli import DEFAULT_URDF
from lolgps_torch.errors import LolgpsError

METHODS = ("lolgps", "naive", "batch")
STREAMS = (
    "paper",
    "square",
)  # "paper": ``lolgps run``'s default stream, no flag; others pass --stream X
VARIANT_NAME = re.compile(r"[A-Za-z0-9_.+]+")  # a folder name's part, without '-'
STREAM_FLAGS = ("--urdf", "--method", "--seed", "--out", "--resume", "--conditions", "--stream")
EVALUATE_FLAGS = ("--run", "--workers")


@dataclass(frozen=True)
class Cell:
    """One run of the grid: a method on an arm (its URDF file) and a stream, with a seed, and
    the name of its variant's flags ("" without variants)."""

    method: str
    urdf: str
    stream: str
    seed: int
    variant: str = ""

    @property
    def arm(self) -> str:
        """The arm's name: the URDF file's stem."""
        return Path(self.urdf).stem

    @property
    def name(self) -> str:
        """The cell's folder name, ``<method>-<arm>-<stream>[-<variant>]-seed<S>``."""
        variant = f"-{self.variant}" if self.variant else ""
        return f"{self.method}-{self.arm}-{self.stream}{variant}-seed{self.seed}"


@dataclass(frozen=True)
class Plan:
    """What every cell's task needs: where it runs and what to pass its commands."""

    out: str  # absolute sweep folder; cell folders go under it
    cwd: str  # the subprocesses' working folder (the driver's, when the node has it)
    conditions: str | None
    evaluate: bool
    stream_flags: tuple[str, ...] = ()
    evaluate_flags: tuple[str, ...] = ()
    variants: tuple[tuple[str, tuple[str, ...]], ...] = ()  # (name, run flags)

    def variant_flags(self, variant: str) -> tuple[str, ...]:
        """The run flags of the variant named ``variant`` (none for "")."""
        return dict(self.variants).get(variant, ())


@dataclass(frozen=True)
class Sweep:
    """A validated sweep: its cells, what they run, and where Ray runs them."""

    cells: tuple[Cell, ...]
    plan: Plan
    address: str | None
    num_cpus: int


@dataclass(frozen=True)
class Outcome:
    """How a cell ended: ``finished``, ``skipped`` (done before) or ``failed`` with its error
    line; ``wall_time`` (s) is that of this attempt."""

    cell: Cell
    status: str
    error: str | None = None
    wall_time: float = 0.0


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are :class:`LolgpsError` (one ``error:`` line)."""

    def error(self, message: str) -> NoReturn:
        raise LolgpsError(f"{message} (see --help)")


# -- the grid -----------------------------------------------------------------------------


def parse_seeds(tokens: Sequence[str]) -> list[int]:
    """The seeds that ``tokens`` name, in order without repeats: each token a seed (``5``), an
    inclusive range (``0-2``) or several of them separated by commas or spaces.

    :param tokens: the ``--seeds`` values as typed
    """
    seeds: list[int] = []
    for part in " ".join(tokens).replace(",", " ").split():
        match = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if match is None:
            raise LolgpsError(
                f"--seeds {part!r}: expected a seed (5), a range (0-2) or a list (0 1 5)"
            )
        low = int(match[1])
        high = low if match[2] is None else int(match[2])
        if high < low:
            raise LolgpsError(f"--seeds {part}: the range is empty")
        seeds.extend(range(low, high + 1))
    if not seeds:
        raise LolgpsError("--seeds: no seed given")
    return list(dict.fromkeys(seeds))


def make_grid(
    seeds: Sequence[int],
    methods: Sequence[str],
    urdfs: Sequence[str],
    streams: Sequence[str],
    variants: Sequence[str] = ("",),
) -> tuple[Cell, ...]:
    """The cells of the grid ``methods x urdfs x streams x variants x seeds``, seeds varying
    fastest.

    :param seeds: run seeds
    :param methods: the run's methods, each one of :data:`METHODS`
    :param urdfs: URDF paths; their stems name the arms and must differ
    :param streams: stream names, each one of :data:`STREAMS`
    :param variants: the variants' names ("": none)
    """
    for method in methods:
        if method not in METHODS:
            raise LolgpsError(f"unknown method {method!r}: choose from {', '.join(METHODS)}")
    for stream in streams:
        if stream not in STREAMS:
            raise LolgpsError(f"unknown stream {stream!r}: choose from {', '.join(STREAMS)}")
    stems = [Path(u).stem for u in urdfs]
    if len(set(stems)) < len(stems):
        raise LolgpsError(f"--urdf files must have different names (cell folders), got {stems}")
    grid = [
        Cell(m, u, s, seed, v)
        for m in dict.fromkeys(methods)
        for u in dict.fromkeys(urdfs)
        for s in dict.fromkeys(streams)
        for v in dict.fromkeys(variants)
        for seed in seeds
    ]
    return tuple(grid)


def split_extra(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """The sweep's own arguments and the run flags after the first ``--``.

    :param argv: the command line without the program name
    """
    argv = list(argv)
    if "--" not in argv:
        return argv, []
    cut = argv.index("--")
    return argv[:cut], argv[cut + 1 :]


def check_flags(flags: Sequence[str], reserved: Sequence[str], command: str) -> None:
    """Raise :class:`LolgpsError` if ``flags`` set one of the ``reserved`` flags, or an
    abbreviation of one, that the sweep sets itself.

    :param flags: the flags passed through to ``command``
    :param reserved: the flags the sweep sets per cell
    :param command: the command's name, for the message
    """
    for token in flags:
        name = token.split("=", 1)[0]
        if not name.startswith("--") or len(name) < 3:
            continue
        for flag in reserved:
            if flag.startswith(name):
                raise LolgpsError(f"{token}: the sweep sets {flag} of {command} itself")


def check_urdf(path: str) -> str:
    """The absolute path of the URDF file ``path``; raise :class:`LolgpsError` if missing.

    :param path: the URDF path as typed
    """
    if not os.path.isfile(path):
        raise LolgpsError(f"--urdf {path}: no such file")
    return os.path.abspath(path)


def check_conditions(path: str | None) -> str | None:
    """The absolute path of a ``--conditions`` file after checking that it holds a non-empty
    JSON list of ``[dx, dy]`` pairs (None passes through).

    :param path: the file as typed, or None for the stream's own conditions
    """
    if path is None:
        return None
    try:
        with open(path) as fh:
            pairs = [(float(dx), float(dy)) for dx, dy in json.load(fh)]
    except OSError as exc:
        raise LolgpsError(f"--conditions {path}: {exc.strerror or exc}") from None
    except (ValueError, TypeError) as exc:
        raise LolgpsError(
            f"--conditions {path}: expected a JSON list of [dx, dy] ({exc})"
        ) from None
    if not pairs:
        raise LolgpsError(f"--conditions {path} is empty")
    return os.path.abspath(path)


def read_variants(path: str | None) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The named run flag sets of a ``--variants`` file (none for None): a non-empty
    JSON object of names (letters, digits, ``_ . +``) to flag strings, none of which sets a
    flag the sweep sets itself.

    :param path: the file as typed, or None
    """
    if path is None:
        return ()
    try:
        with open(path) as fh:
            data = json.load(fh)
    except OSError as exc:
        raise LolgpsError(f"--variants {path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise LolgpsError(f"--variants {path}: not JSON ({exc})") from None
    if not isinstance(data, dict) or not data:
        raise LolgpsError(f"--variants {path}: expected a JSON object of names to flags")
    variants = []
    for name, flags in data.items():
        if not VARIANT_NAME.fullmatch(name):
            raise LolgpsError(f"--variants {path}: name {name!r} may use only A-Z a-z 0-9 _ . +")
        if not isinstance(flags, str):
            raise LolgpsError(f"--variants {path}: {name}'s flags must be one string")
        try:
            split = tuple(shlex.split(flags))
        except ValueError as exc:
            raise LolgpsError(f"--variants {path}: {name}: {exc}") from None
        check_flags(split, STREAM_FLAGS, "lolgps run")
        variants.append((name, split))
    return tuple(variants)


def check_out(path: str) -> str:
    """The absolute path of the sweep folder ``path``, created if missing, after checking that
    a file can be written in it. Call it last, once every other input has been checked.

    :param path: ``--out`` as typed
    """
    out = Path(path).absolute()
    if out.exists() and not out.is_dir():
        raise LolgpsError(f"--out {path} is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise LolgpsError(f"--out {path}: cannot write there ({exc.strerror or exc})") from None
    return str(out)


def check_address(address: str | None) -> None:
    """Raise :class:`LolgpsError` if ``address`` names a ``host:port`` (optionally
    ``ray://host:port``) where nothing answers within 5 s (``auto`` and None pass: Ray itself
    finds the cluster, or starts a local one).

    :param address: ``--address`` as typed, or None
    """
    if address is None or address == "auto":
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise LolgpsError(f"--address {address}: expected auto or HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=5.0).close()
    except OSError as exc:
        raise LolgpsError(f"--address {address}: no Ray head answers ({exc})") from None


def make_sweep(args: argparse.Namespace, extra: Sequence[str]) -> Sweep:
    """Check every input of the sweep and return it; raise :class:`LolgpsError` on the first
    bad one, before any work.

    :param args: the parsed sweep arguments (see :func:`build_parser`)
    :param extra: the run flags after ``--``
    """
    seeds = parse_seeds(args.seeds)
    urdfs = [check_urdf(u) for u in args.urdf]
    variants = read_variants(args.variants)
    names = [name for name, _ in variants] or [""]
    cells = make_grid(seeds, args.methods, urdfs, args.stream, names)
    try:
        evaluate_flags = shlex.split(args.evaluate_args or "")
    except ValueError as exc:
        raise LolgpsError(f"--evaluate-args {args.evaluate_args!r}: {exc}") from None
    check_flags(extra, STREAM_FLAGS, "lolgps run")
    check_flags(evaluate_flags, EVALUATE_FLAGS, "lolgps evaluate")
    if evaluate_flags and not args.evaluate:
        raise LolgpsError("--evaluate-args needs --evaluate")
    if args.address is not None and args.num_cpus is not None:
        raise LolgpsError("--num-cpus sizes a local Ray instance: drop it with --address")
    check_address(args.address)
    num_cpus = args.num_cpus if args.num_cpus is not None else os.cpu_count() or 1
    if num_cpus < 1:
        raise LolgpsError(f"--num-cpus {num_cpus}: must be >= 1")
    conditions = check_conditions(args.conditions)
    plan = Plan(
        out=check_out(args.out),
        cwd=os.getcwd(),
        conditions=conditions,
        evaluate=args.evaluate,
        stream_flags=tuple(extra),
        evaluate_flags=tuple(evaluate_flags),
        variants=variants,
    )
    return Sweep(cells, plan, args.address, num_cpus)


def build_parser(prog: str | None = None) -> argparse.ArgumentParser:
    """The sweep's command line (run flags for every cell follow a ``--``), ``prog`` its name
    in the usage (default: the script's)."""
    parser = _Parser(
        prog=prog,
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--seeds", nargs="+", default=["0"], help="e.g. 0-2 or 0 1 5 (default 0)")
    parser.add_argument(
        "--methods", nargs="+", default=["lolgps"], help=f"of {', '.join(METHODS)} (default lolgps)"
    )
    parser.add_argument(
        "--urdf", nargs="+", default=[DEFAULT_URDF], help=f"arms (default {DEFAULT_URDF})"
    )
    parser.add_argument(
        "--stream", nargs="+", choices=STREAMS, default=["paper"], help="streams (default paper)"
    )
    parser.add_argument("--out", required=True, help="sweep folder: one subfolder per cell")
    parser.add_argument("--conditions", default=None, help="the run's --conditions for all cells")
    parser.add_argument(
        "--variants",
        default=None,
        help='JSON file of named run flag sets, {"name": "--flag value", ...}: '
        "each cell runs once per variant",
    )
    parser.add_argument(
        "--evaluate", action="store_true", help="evaluate each cell (lolgps evaluate --workers 1)"
    )
    parser.add_argument(
        "--evaluate-args",
        default=None,
        help="more evaluate flags in one string, e.g. --evaluate-args='--areas 3'",
    )
    parser.add_argument(
        "--address", default=None, help="join this Ray cluster (e.g. auto) instead of a local one"
    )
    parser.add_argument(
        "--num-cpus", type=int, default=None, help="CPUs of the local Ray instance (default: all)"
    )
    return parser
