"""Sweeps of ``run_stream.py`` over a grid of seeds x methods x arms x streams, on Ray.

    python scripts/sweep.py --seeds 0-2 --methods lolgps naive batch \\
        --urdf robots/kuka_peg.urdf --out runs/sweep1 [--evaluate] [--address auto] \\
        [-- extra run_stream flags]

Each cell of the grid is one ``run_stream.py`` run in its own folder under ``--out``, named
``<method>-<urdf stem>-<stream>-seed<S>``. A Ray task (one CPU) runs the cell's scripts as
subprocesses: ``run_stream.py`` (with ``--resume`` when the folder already holds config.json),
then, with ``--evaluate``, ``evaluate.py --workers 1``. No PyBullet client crosses a process,
and a cell folder is exactly a command-line run's, so it resumes the same way. The scripts'
output goes to the cell's ``sweep.log``, and the wall time of its attempts to
``sweep_cell.json``.

A failed cell is retried once and reported with its last ``error:`` line; the others carry
on. Rerunning the same command skips finished cells (summary.json, and eval.json with
``--evaluate``) and resumes interrupted ones. At the end ``--out`` holds ``sweep.json`` (the
grid and each cell's outcome) and the aggregate over seeds: ``summary.md``, ``summary.csv``
and ``summary.png``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import logging
import math
import os
import re
import shlex
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from types import ModuleType
from typing import IO, Any, NoReturn

from lolgps_torch.errors import LolgpsError

METHODS = ("lolgps", "naive", "batch")
STREAMS = ("paper",)  # "paper": run_stream's default stream, no flag; others pass --stream X
DEFAULT_URDF = "robots/kuka_peg.urdf"
SWEEP_FILE = "sweep.json"
CELL_FILE = "sweep_cell.json"
LOG_FILE = "sweep.log"
ATTEMPTS = 2  # a failed cell is retried once
STREAM_FLAGS = ("--urdf", "--method", "--seed", "--out", "--resume", "--conditions", "--stream")
EVALUATE_FLAGS = ("--run", "--workers")
INSTALL_HINT = "Ray is not installed: pip install -e '.[ray]'"


@dataclass(frozen=True)
class Cell:
    """One run of the grid: a method on an arm (its URDF file) and a stream, with a seed."""

    method: str
    urdf: str
    stream: str
    seed: int

    @property
    def arm(self) -> str:
        """The arm's name: the URDF file's stem."""
        return Path(self.urdf).stem

    @property
    def name(self) -> str:
        """The cell's folder name, ``<method>-<arm>-<stream>-seed<S>``."""
        return f"{self.method}-{self.arm}-{self.stream}-seed{self.seed}"


@dataclass(frozen=True)
class Plan:
    """What every cell's task needs: where the scripts are and what to pass them."""

    scripts: str  # folder holding run_stream.py and evaluate.py
    out: str  # absolute sweep folder; cell folders go under it
    cwd: str  # the subprocesses' working folder (the driver's, when the node has it)
    conditions: str | None
    evaluate: bool
    stream_flags: tuple[str, ...] = ()
    evaluate_flags: tuple[str, ...] = ()


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
    seeds: Sequence[int], methods: Sequence[str], urdfs: Sequence[str], streams: Sequence[str]
) -> tuple[Cell, ...]:
    """The cells of the grid ``methods x urdfs x streams x seeds``, seeds varying fastest.

    :param seeds: run seeds
    :param methods: run_stream methods, each one of :data:`METHODS`
    :param urdfs: URDF paths; their stems name the arms and must differ
    :param streams: stream names, each one of :data:`STREAMS`
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
        Cell(m, u, s, seed)
        for m in dict.fromkeys(methods)
        for u in dict.fromkeys(urdfs)
        for s in dict.fromkeys(streams)
        for seed in seeds
    ]
    return tuple(grid)


def split_extra(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """The sweep's own arguments and the run_stream flags after the first ``--``.

    :param argv: the command line without the program name
    """
    argv = list(argv)
    if "--" not in argv:
        return argv, []
    cut = argv.index("--")
    return argv[:cut], argv[cut + 1 :]


def check_flags(flags: Sequence[str], reserved: Sequence[str], script: str) -> None:
    """Raise :class:`LolgpsError` if ``flags`` set one of the ``reserved`` flags, or an
    abbreviation of one, that the sweep sets itself.

    :param flags: the flags passed through to ``script``
    :param reserved: the flags the sweep sets per cell
    :param script: the script's name, for the message
    """
    for token in flags:
        name = token.split("=", 1)[0]
        if not name.startswith("--") or len(name) < 3:
            continue
        for flag in reserved:
            if flag.startswith(name):
                raise LolgpsError(f"{token}: the sweep sets {flag} of {script} itself")


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


def default_scripts() -> str:
    """The repository's ``scripts`` folder, next to this package."""
    return str(Path(__file__).resolve().parents[1] / "scripts")


def make_sweep(args: argparse.Namespace, extra: Sequence[str], scripts: str) -> Sweep:
    """Check every input of the sweep and return it; raise :class:`LolgpsError` on the first
    bad one, before any work.

    :param args: the parsed sweep arguments (see :func:`build_parser`)
    :param extra: the run_stream flags after ``--``
    :param scripts: the folder holding run_stream.py and evaluate.py
    """
    seeds = parse_seeds(args.seeds)
    urdfs = [check_urdf(u) for u in args.urdf]
    cells = make_grid(seeds, args.methods, urdfs, args.stream)
    try:
        evaluate_flags = shlex.split(args.evaluate_args or "")
    except ValueError as exc:
        raise LolgpsError(f"--evaluate-args {args.evaluate_args!r}: {exc}") from None
    check_flags(extra, STREAM_FLAGS, "run_stream.py")
    check_flags(evaluate_flags, EVALUATE_FLAGS, "evaluate.py")
    if evaluate_flags and not args.evaluate:
        raise LolgpsError("--evaluate-args needs --evaluate")
    if args.address is not None and args.num_cpus is not None:
        raise LolgpsError("--num-cpus sizes a local Ray instance: drop it with --address")
    check_address(args.address)
    num_cpus = args.num_cpus if args.num_cpus is not None else os.cpu_count() or 1
    if num_cpus < 1:
        raise LolgpsError(f"--num-cpus {num_cpus}: must be >= 1")
    for script in ("run_stream.py", "evaluate.py"):
        if not os.path.isfile(os.path.join(scripts, script)):
            raise LolgpsError(f"{script} not found in {scripts}")
    conditions = check_conditions(args.conditions)
    plan = Plan(
        scripts=os.path.abspath(scripts),
        out=check_out(args.out),
        cwd=os.getcwd(),
        conditions=conditions,
        evaluate=args.evaluate,
        stream_flags=tuple(extra),
        evaluate_flags=tuple(evaluate_flags),
    )
    return Sweep(cells, plan, args.address, num_cpus)


def build_parser() -> argparse.ArgumentParser:
    """The sweep's command line (run_stream flags for every cell follow a ``--``)."""
    parser = _Parser(
        prog="sweep.py",
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
    parser.add_argument("--conditions", default=None, help="run_stream --conditions for all cells")
    parser.add_argument(
        "--evaluate", action="store_true", help="evaluate each cell (evaluate.py --workers 1)"
    )
    parser.add_argument(
        "--evaluate-args",
        default=None,
        help="more evaluate.py flags in one string, e.g. --evaluate-args='--areas 3'",
    )
    parser.add_argument(
        "--address", default=None, help="join this Ray cluster (e.g. auto) instead of a local one"
    )
    parser.add_argument(
        "--num-cpus", type=int, default=None, help="CPUs of the local Ray instance (default: all)"
    )
    return parser


# -- one cell (runs inside a Ray task) ------------------------------------------------------


def cell_state(folder: Path, evaluate: bool) -> str:
    """What a cell folder still needs: ``done``, ``evaluate`` (the run finished but has no
    eval.json), ``resume`` (config.json but no summary.json) or ``new``.

    :param folder: the cell's folder
    :param evaluate: whether the sweep evaluates its cells
    """
    if (folder / "summary.json").is_file():
        return "evaluate" if evaluate and not (folder / "eval.json").is_file() else "done"
    return "resume" if (folder / "config.json").is_file() else "new"


def stream_command(cell: Cell, plan: Plan, resume: bool) -> list[str]:
    """The ``run_stream.py`` command line of ``cell``.

    :param cell: the cell
    :param plan: the sweep's scripts, folder and pass-through flags
    :param resume: continue the run already in the cell's folder
    """
    command = [sys.executable, os.path.join(plan.scripts, "run_stream.py")]
    command += ["--urdf", cell.urdf, "--method", cell.method, "--seed", str(cell.seed)]
    command += ["--out", os.path.join(plan.out, cell.name)]
    if cell.stream != "paper":
        command += ["--stream", cell.stream]
    if plan.conditions is not None:
        command += ["--conditions", plan.conditions]
    return command + list(plan.stream_flags) + (["--resume"] if resume else [])


def evaluate_command(cell: Cell, plan: Plan) -> list[str]:
    """The ``evaluate.py`` command line of ``cell`` (one worker: the task holds one CPU).

    :param cell: the cell
    :param plan: the sweep's scripts, folder and pass-through flags
    """
    run = os.path.join(plan.out, cell.name)
    script = os.path.join(plan.scripts, "evaluate.py")
    return [sys.executable, script, "--run", run, "--workers", "1", *plan.evaluate_flags]


def error_line(stderr: str, returncode: int) -> str:
    """A failed script's one-line reason: its last ``error:`` line, else its last line of
    stderr (a traceback's exception), else its exit status.

    :param stderr: what the script wrote to stderr
    :param returncode: its exit status (negative: killed by that signal)
    """
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:") or ": error:" in line]
    if errors:
        return errors[-1]
    if lines:
        return lines[-1]
    if returncode < 0:
        return f"killed by signal {-returncode}"
    return f"exit status {returncode}"


def run_logged(command: list[str], folder: Path, cwd: str) -> str | None:
    """Run ``command`` with its output appended to ``folder/sweep.log``; None if it
    succeeded, else its :func:`error_line`.

    :param command: the command line
    :param folder: the cell folder (created if missing)
    :param cwd: the working folder, used when it exists on this node
    """
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / LOG_FILE, "a") as log:
        log.write(f"$ {shlex.join(command)}\n")
        log.flush()
        proc = subprocess.run(
            command,
            stdout=log,
            stderr=subprocess.PIPE,
            text=True,
            cwd=cwd if os.path.isdir(cwd) else None,
            check=False,
        )
        log.write(proc.stderr)
        log.write(f"# exit status {proc.returncode}\n")
    return None if proc.returncode == 0 else error_line(proc.stderr, proc.returncode)


def add_wall_time(folder: Path, seconds: float) -> None:
    """Add ``seconds`` to the wall time recorded in ``folder/sweep_cell.json``.

    :param folder: the cell folder (nothing is recorded if it does not exist)
    :param seconds: the wall time of one attempt
    """
    path = folder / CELL_FILE
    try:
        total = float(json.loads(path.read_text())["wall_time"]) if path.is_file() else 0.0
    except (OSError, ValueError, KeyError, TypeError):
        total = 0.0
    with contextlib.suppress(OSError):
        write_json(path, {"wall_time": total + seconds})


def execute_cell(cell: Cell, plan: Plan) -> Outcome:
    """Run what ``cell`` still needs (its stream, resumed if interrupted, then its evaluation)
    as subprocesses, and return how it ended. This is the body of the sweep's Ray task.

    :param cell: the cell
    :param plan: the sweep's scripts, folder and pass-through flags
    """
    folder = Path(plan.out) / cell.name
    start = time.monotonic()
    state = cell_state(folder, plan.evaluate)
    error = None
    try:
        if state in ("new", "resume"):
            error = run_logged(stream_command(cell, plan, state == "resume"), folder, plan.cwd)
        if error is None and plan.evaluate and state != "done":
            error = run_logged(evaluate_command(cell, plan), folder, plan.cwd)
    except OSError as exc:
        error = f"{type(exc).__name__}: {exc}"
    wall = time.monotonic() - start
    add_wall_time(folder, wall)
    return Outcome(cell, "failed" if error else "finished", error, wall)


# -- running the grid on Ray -------------------------------------------------------------


def import_ray() -> ModuleType:
    """The ``ray`` module; raise :class:`LolgpsError` with the install command without it."""
    try:
        import ray
    except ImportError:
        raise LolgpsError(INSTALL_HINT) from None
    return ray


@contextlib.contextmanager
def ray_session(ray: ModuleType, address: str | None, num_cpus: int) -> Iterator[int]:
    """Connect to Ray for the block and yield its CPU count: join the cluster at ``address``,
    or start a local instance with ``num_cpus`` CPUs; an instance already connected is used
    as it is (and left running).

    :param ray: the ray module
    :param address: a cluster address (e.g. ``auto``), or None for a local instance
    :param num_cpus: CPUs of a local instance
    """
    started = not ray.is_initialized()
    if started:
        options: dict[str, Any] = {"logging_level": logging.ERROR}
        if address is None:
            options.update(num_cpus=num_cpus, include_dashboard=False)
        try:
            ray.init(address=address, **options)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"the Ray cluster at {address}" if address else "a local Ray instance"
            raise LolgpsError(
                f"cannot start {where}: {str(exc).strip().splitlines()[-1]}"
            ) from None
    try:
        yield max(1, int(ray.cluster_resources().get("CPU", 1)))
    finally:
        if started:
            ray.shutdown()


def format_duration(seconds: float | None) -> str:
    """``seconds`` as ``1h02m``, ``3m05s`` or ``42s`` (``?`` when unknown).

    :param seconds: a duration, or None
    """
    if seconds is None or not math.isfinite(seconds):
        return "?"
    s = int(round(seconds))
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    if s >= 60:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s}s"


class Progress:
    """The sweep's progress line: cells done, running and failed, and an ETA from the rate at
    which this session has finished cells. On a terminal it is one line rewritten in place;
    otherwise each event prints a line."""

    def __init__(self, total: int, done: int, slots: int, stream: IO[str] | None = None) -> None:
        """
        :param total: cells in the grid
        :param done: cells already finished before this session
        :param slots: cells that can run at once (the cluster's CPUs)
        :param stream: where to write (default stdout)
        """
        self.total, self.done, self.failed, self.slots = total, done, 0, slots
        self.stream = stream if stream is not None else sys.stdout
        self.tty = self.stream.isatty()
        self.start, self.ended, self.last_end = time.monotonic(), 0, 0.0

    def status(self, pending: int) -> str:
        """The status line with ``pending`` cells submitted and not yet ended."""
        running = min(pending, self.slots)
        eta = None
        if self.ended:  # this session's time per cell so far, counting down between events
            per_cell = (self.last_end - self.start) / self.ended
            eta = max(0.0, self.start + per_cell * (self.ended + pending) - time.monotonic())
        return (
            f"[{self.done}/{self.total} done, {running} running, {self.failed} failed, "
            f"ETA {format_duration(0.0 if not pending else eta)}]"
        )

    def event(self, message: str, pending: int) -> None:
        """Report ``message`` with the status line.

        :param message: what happened
        :param pending: cells submitted and not yet ended
        """
        if self.tty:
            self.stream.write(f"\r\033[K{message}\n{self.status(pending)}")
        else:
            self.stream.write(f"{self.status(pending)} {message}\n")
        self.stream.flush()

    def tick(self, pending: int) -> None:
        """Refresh the status line (on a terminal only)."""
        if self.tty:
            self.stream.write(f"\r\033[K{self.status(pending)}")
            self.stream.flush()

    def end(self, outcome: Outcome, pending: int) -> None:
        """Count a cell that ended and report it.

        :param outcome: how it ended
        :param pending: cells still submitted
        """
        self.ended, self.last_end = self.ended + 1, time.monotonic()
        if outcome.status == "failed":
            self.failed += 1
            self.event(f"{outcome.cell.name} FAILED: {outcome.error}", pending)
        else:
            self.done += 1
            wall = format_duration(outcome.wall_time)
            self.event(f"{outcome.cell.name} finished in {wall}", pending)

    def close(self) -> None:
        """End the status line."""
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _result(ray: ModuleType, ref: Any, cell: Cell) -> Outcome:
    """The outcome a finished Ray task returned, or a failure if the task itself died."""
    try:
        outcome: Outcome = ray.get(ref)
    except ray.exceptions.RayError as exc:
        lines = [line for line in str(exc).splitlines() if line.strip()]
        return Outcome(cell, "failed", lines[-1] if lines else type(exc).__name__)
    return outcome


def run_cells(
    ray: ModuleType, cells: Sequence[Cell], plan: Plan, progress: Progress
) -> list[Outcome]:
    """Run ``cells`` as Ray tasks of one CPU each, a failed one retried once, and return their
    final outcomes in the order they ended. Ctrl-C cancels the tasks (and their scripts).

    :param ray: the ray module, connected
    :param cells: the cells to run
    :param plan: the sweep's scripts, folder and pass-through flags
    :param progress: the progress line
    """
    task = ray.remote(num_cpus=1, max_retries=0)(execute_cell)
    pending = {task.remote(cell, plan): (cell, 1) for cell in cells}
    outcomes: list[Outcome] = []
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                cell, attempt = pending.pop(ref)
                outcome = _result(ray, ref, cell)
                if outcome.status == "failed" and attempt < ATTEMPTS:
                    pending[task.remote(cell, plan)] = (cell, attempt + 1)
                    progress.event(f"{cell.name} failed ({outcome.error}); retrying", len(pending))
                    continue
                outcomes.append(outcome)
                progress.end(outcome, len(pending))
            progress.tick(len(pending))
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref)
        ray.wait(list(pending), num_returns=len(pending), timeout=10.0)
        raise
    return outcomes


# -- aggregation ----------------------------------------------------------------------------

# (key, markdown heading, format) of the aggregated metrics
METRICS = (
    ("train_success", "training success", ".2f"),
    ("test_success", "test-area success", ".2f"),
    ("forgetting_area0", "forgetting area 0", "+.2f"),
    ("forgetting_areas", "forgetting (mean)", "+.2f"),
    ("rollouts", "rollouts", ".0f"),
    ("wall_time", "wall time (s)", ".0f"),
)


def read_json(path: Path) -> Any:
    """The JSON in ``path``; raise :class:`LolgpsError` if unreadable.

    :param path: the file
    """
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise LolgpsError(f"cannot read {path}: {exc}") from None


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` to ``path`` as JSON through a temporary sibling, so that a reader never
    sees a partial file.

    :param path: the file
    :param data: JSON-serialisable data
    """
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


def eval_metrics(evaluation: dict[str, Any]) -> dict[str, float | None]:
    """The headline test-area numbers of an eval.json: the final policy's success rate
    averaged over the test areas (``average_final_success``), and the forgetting of success
    on area 0 and its mean over the trained areas (positive: worse at the end than right after
    the stage that trained the area).

    :param evaluation: the parsed eval.json
    """
    metrics = evaluation["metrics"]
    forgot = (metrics.get("forgetting") or {}).get("success_rate") or {}
    per_area = forgot.get("per_area") or [None]
    return {
        "test_success": metrics.get("average_final_success"),
        "forgetting_area0": per_area[0],
        "forgetting_areas": forgot.get("mean"),
    }


def cell_metrics(folder: Path) -> dict[str, float | None] | None:
    """The per-run numbers of a cell folder, None if its run has not finished: the fraction of
    training positions where the final policy alone succeeds (``policy_success_end``), the
    rollouts (``sum of iterations x samples per iteration``), the sweep's wall time, and with
    an eval.json its :func:`eval_metrics`.

    :param folder: the cell folder
    """
    if not (folder / "summary.json").is_file():
        return None
    entries = read_json(folder / "summary.json")["conditions"]
    samples = int(read_json(folder / "config.json")["stream"]["local"]["samples"])
    row: dict[str, float | None] = {key: None for key, _, _ in METRICS}
    if entries:
        row["train_success"] = statistics.fmean(bool(e["policy_success_end"]) for e in entries)
    row["rollouts"] = float(sum(int(e["iterations"]) for e in entries) * samples)
    if (folder / CELL_FILE).is_file():
        row["wall_time"] = float(read_json(folder / CELL_FILE)["wall_time"])
    if (folder / "eval.json").is_file():
        row.update(eval_metrics(read_json(folder / "eval.json")))
    return row


def mean_sd(values: Sequence[float | None]) -> tuple[float | None, float | None, int]:
    """Mean and sample standard deviation (``n - 1``) of the defined, finite ``values``, and
    their count; the sd is None below two values, both are None without any.

    :param values: one number per seed, None where unavailable
    """
    defined = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not defined:
        return None, None, 0
    sd = statistics.stdev(defined) if len(defined) > 1 else None
    return statistics.fmean(defined), sd, len(defined)


def aggregate(cells: Sequence[Cell], out: Path) -> list[dict[str, Any]]:
    """One row per method x arm x stream, in grid order, over the seeds whose run finished:
    ``seeds`` (their count) and ``<metric>_mean``, ``<metric>_sd``, ``<metric>_n`` for each of
    :data:`METRICS`. Groups without a finished run are left out.

    :param cells: the grid
    :param out: the sweep folder holding the cell folders
    """
    groups: dict[tuple[str, str, str], list[dict[str, float | None]]] = {}
    for cell in cells:
        found = cell_metrics(out / cell.name)
        group = groups.setdefault((cell.method, cell.arm, cell.stream), [])
        if found is not None:
            group.append(found)
    rows = []
    for (method, arm, stream), found_rows in groups.items():
        if not found_rows:
            continue
        row: dict[str, Any] = {"method": method, "arm": arm, "stream": stream}
        row["seeds"] = len(found_rows)
        for key, _, _ in METRICS:
            mean, sd, n = mean_sd([r[key] for r in found_rows])
            row.update({f"{key}_mean": mean, f"{key}_sd": sd, f"{key}_n": n})
        rows.append(row)
    return rows


def format_mean_sd(mean: float | None, sd: float | None, fmt: str) -> str:
    """``mean ± sd`` in ``fmt`` (``-`` without a mean, the mean alone without an sd).

    :param mean: the mean, or None
    :param sd: the standard deviation, or None
    :param fmt: a format spec such as ``.2f``
    """
    if mean is None:
        return "-"
    if sd is None:
        return f"{mean:{fmt}}"
    return f"{mean:{fmt}} ± {sd:{fmt.lstrip('+')}}"


def markdown_table(rows: Sequence[dict[str, Any]], failed: Sequence[Outcome]) -> str:
    """The aggregate as a markdown table, mean ± sd over seeds, with the failed cells after it.

    :param rows: from :func:`aggregate`
    :param failed: the cells that failed in this session
    """
    heads = ["method", "arm", "stream", "seeds", *(head for _, head, _ in METRICS)]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for row in rows:
        cells = [row["method"], row["arm"], row["stream"], str(row["seeds"])]
        cells += [format_mean_sd(row[f"{k}_mean"], row[f"{k}_sd"], f) for k, _, f in METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Mean ± sd over seeds. Training success: fraction of training positions where the final "
        "policy alone succeeds. Test-area success: the final policy's success rate averaged "
        "over the test areas (eval.json). Forgetting: drop in success rate between the stage "
        "that trained an area and the end (positive: forgot). Rollouts: iterations x samples.",
    ]
    if failed:
        lines += ["", "Failed cells:", ""]
        lines += [f"- `{o.cell.name}`: {o.error}" for o in failed]
    return "\n".join(lines) + "\n"


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """The aggregate as CSV: method, arm, stream, seeds, then mean, sd and n per metric.

    :param path: the file
    :param rows: from :func:`aggregate`
    """
    fields = ["method", "arm", "stream", "seeds"]
    fields += [f"{k}_{s}" for k, _, _ in METRICS for s in ("mean", "sd", "n")]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        for row in rows:
            writer.writerow({f: "" if row[f] is None else row[f] for f in fields})


def plot_summary(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    """Bar charts of training success and rollouts per method x arm (x stream), with sd error
    bars, saved to ``path``.

    :param path: the image file
    :param rows: from :func:`aggregate`
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    streams = {row["stream"] for row in rows}
    labels = [
        f"{r['method']}\n{r['arm']}" + (f"\n{r['stream']}" if len(streams) > 1 else "")
        for r in rows
    ]
    fig, axes = plt.subplots(1, 2, figsize=(max(6.0, 1.6 * len(rows) + 2.0), 3.8))
    for ax, (key, title) in zip(
        axes, (("train_success", "training success"), ("rollouts", "rollouts")), strict=True
    ):
        means = [row[f"{key}_mean"] or 0.0 for row in rows]
        sds = [row[f"{key}_sd"] or 0.0 for row in rows]
        ax.bar(range(len(rows)), means, yerr=sds, capsize=4, color="tab:blue")
        ax.set_xticks(range(len(rows)), labels, fontsize=8)
        ax.set_title(f"{title} (mean ± sd over seeds)", fontsize=9)
    axes[0].set_ylim(0.0, 1.05)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_summaries(sweep: Sweep, failed: Sequence[Outcome]) -> list[Path]:
    """Write summary.md, summary.csv and (with any finished run) summary.png into the sweep
    folder and return their paths.

    :param sweep: the sweep
    :param failed: the cells that failed in this session
    """
    out = Path(sweep.plan.out)
    rows = aggregate(sweep.cells, out)
    (out / "summary.md").write_text(markdown_table(rows, failed))
    write_csv(out / "summary.csv", rows)
    written = [out / "summary.md", out / "summary.csv"]
    if rows:
        plot_summary(out / "summary.png", rows)
        written.append(out / "summary.png")
    return written


# -- the command ----------------------------------------------------------------------------


def write_sweep_file(sweep: Sweep, outcomes: dict[Cell, Outcome]) -> None:
    """Record the grid and each cell's status (``pending`` until it ends) in sweep.json.

    :param sweep: the sweep
    :param outcomes: the cells that ended so far
    """
    cells = []
    for cell in sweep.cells:
        outcome = outcomes.get(cell)
        entry = {"name": cell.name, "arm": cell.arm, **asdict(cell)}
        entry["status"] = outcome.status if outcome else "pending"
        entry["error"] = outcome.error if outcome else None
        cells.append(entry)
    data = {
        "seeds": list(dict.fromkeys(c.seed for c in sweep.cells)),
        "methods": list(dict.fromkeys(c.method for c in sweep.cells)),
        "urdfs": list(dict.fromkeys(c.urdf for c in sweep.cells)),
        "streams": list(dict.fromkeys(c.stream for c in sweep.cells)),
        "plan": asdict(sweep.plan),
        "cells": cells,
    }
    write_json(Path(sweep.plan.out) / SWEEP_FILE, data)


def main(argv: Sequence[str], scripts: str | None = None) -> int:
    """Run a sweep from its command line and return the exit status: 0, or 1 if a cell
    finally failed. Bad input raises :class:`LolgpsError` before any work.

    :param argv: the command line without the program name
    :param scripts: the folder holding run_stream.py and evaluate.py (default: the
        repository's, next to this package)
    """
    own, extra = split_extra(argv)
    args = build_parser().parse_args(own)
    ray = import_ray()
    sweep = make_sweep(args, extra, scripts or default_scripts())
    out = Path(sweep.plan.out)
    states = {c: cell_state(out / c.name, sweep.plan.evaluate) for c in sweep.cells}
    outcomes = {c: Outcome(c, "skipped") for c, state in states.items() if state == "done"}
    todo = [c for c in sweep.cells if c not in outcomes]
    write_sweep_file(sweep, outcomes)
    counts = Counter(states.values())
    print(
        f"{len(sweep.cells)} cells in {out}: {counts['done']} finished before (skipped), "
        f"{counts['resume']} to resume, {counts['evaluate']} to evaluate, {counts['new']} new",
        flush=True,
    )
    if todo:
        with ray_session(ray, sweep.address, sweep.num_cpus) as slots:
            progress = Progress(len(sweep.cells), len(outcomes), slots)
            try:
                ended = run_cells(ray, todo, sweep.plan, progress)
            finally:
                progress.close()
        outcomes.update({o.cell: o for o in ended})
    write_sweep_file(sweep, outcomes)
    failed = [o for o in outcomes.values() if o.status == "failed"]
    written = write_summaries(sweep, failed)
    print(f"wrote {', '.join(str(p) for p in written)}")
    if failed:
        print(f"{len(failed)} of {len(sweep.cells)} cells failed:", file=sys.stderr)
        for o in failed:
            print(f"  {o.cell.name}: {o.error}", file=sys.stderr)
    return 1 if failed else 0
