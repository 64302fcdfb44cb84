"""One cell of a sweep, run inside a Ray task: what its folder still needs, the command lines
of its ``lolgps`` commands (``python -m lolgps_torch``), their runs logged to the cell's
sweep.log, and its wall time in sweep_cell.json."""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from lolgps_torch.data.run_folder import RunFolder, write_json
from lolgps_torch.sweep.grid import Cell, Outcome, Plan

CELL_FILE = "sweep_cell.json"
LOG_FILE = "sweep.log"


def cell_state(folder: Path, evaluate: bool) -> str:
    """What a cell folder still needs: ``done``, ``evaluate`` (the run finished but has no
    eval.json), ``resume`` (config.json but no summary.json) or ``new``.

    :param folder: the cell's folder
    :param evaluate: whether the sweep evaluates its cells
    """
    run = RunFolder(folder)
    if run.summary_path.is_file():
        return "evaluate" if evaluate and not run.eval_path.is_file() else "done"
    return "resume" if run.config_path.is_file() else "new"


COMMAND = (sys.executable, "-m", "lolgps_torch")  # ``lolgps`` in this interpreter


def stream_command(cell: Cell, plan: Plan, resume: bool) -> list[str]:
    """The ``lolgps run`` command line of ``cell``.

    :param cell: the cell
    :param plan: the sweep's folder and pass-through flags
    :param resume: continue the run already in the cell's folder
    """
    command = [*COMMAND, "run"]
    command += ["--urdf", cell.urdf, "--method", cell.method, "--seed", str(cell.seed)]
    command += ["--out", os.path.join(plan.out, cell.name), "--workers", "1"]  # a CPU a cell
    if cell.stream != "paper":
        command += ["--stream", cell.stream]
    if plan.conditions is not None:
        command += ["--conditions", plan.conditions]
    command += [*plan.stream_flags, *plan.variant_flags(cell.variant)]
    return command + (["--resume"] if resume else [])


def evaluate_command(cell: Cell, plan: Plan) -> list[str]:
    """The ``lolgps evaluate`` command line of ``cell`` (one worker: the task holds one CPU).

    :param cell: the cell
    :param plan: the sweep's folder and pass-through flags
    """
    run = os.path.join(plan.out, cell.name)
    return [*COMMAND, "evaluate", "--run", run, "--workers", "1", *plan.evaluate_flags]


def error_line(stderr: str, returncode: int) -> str:
    """A failed command's one-line reason: its last ``error:`` line, else its last line of
    stderr (a traceback's exception), else its exit status.

    :param stderr: what the command wrote to stderr
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
    :param plan: the sweep's folder and pass-through flags
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
