"""A sweep on Ray: its cells as tasks of one CPU each (a failed one retried once) with a
progress line, and the command that skips finished cells, resumes the others and records the
grid in sweep.json before writing the summaries."""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from types import ModuleType
from typing import IO, Any

from lolgps_torch.cluster import import_ray, ray_connection
from lolgps_torch.sweep.cells import cell_state, execute_cell, write_json
from lolgps_torch.sweep.grid import (
    Cell,
    Outcome,
    Plan,
    Sweep,
    build_parser,
    make_sweep,
    split_extra,
)
from lolgps_torch.sweep.summary import write_summaries

SWEEP_FILE = "sweep.json"
ATTEMPTS = 2  # a failed cell is retried once


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
    which this sweep has finished cells. On a terminal it is one line rewritten in place;
    otherwise each event prints a line."""

    def __init__(self, total: int, done: int, slots: int, stream: IO[str] | None = None) -> None:
        """
        :param total: cells in the grid
        :param done: cells already finished before this sweep started
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
        if self.ended:  # this sweep's time per cell so far, counting down between events
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
    final outcomes in the order they ended. Ctrl-C cancels the tasks (and their commands).

    :param ray: the ray module, connected
    :param cells: the cells to run
    :param plan: the sweep's folder and pass-through flags
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


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> int:
    """Run a sweep from its command line and return the exit status: 0, or 1 if a cell
    finally failed. Bad input raises :class:`LolgpsError` before any work.

    :param argv: the command line without the program name (default: this process's)
    :param prog: the command's name in the usage (default: the script's)
    """
    own, extra = split_extra(sys.argv[1:] if argv is None else argv)
    args = build_parser(prog).parse_args(own)
    ray = import_ray()
    sweep = make_sweep(args, extra)
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
        with ray_connection(ray, sweep.address, sweep.num_cpus) as slots:
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
