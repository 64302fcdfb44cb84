"""Sweeps of ``lolgps run`` over a grid of seeds x methods x arms x streams, on Ray
(``lolgps sweep``; the command line is described in :mod:`lolgps_torch.sweep.grid`):
:mod:`~lolgps_torch.sweep.grid` parses and checks the grid and names its cells,
:mod:`~lolgps_torch.sweep.cells` runs one cell inside a Ray task,
:mod:`~lolgps_torch.sweep.run` runs the grid on Ray and is the command, and
:mod:`~lolgps_torch.sweep.summary` aggregates the finished cells over seeds."""

from lolgps_torch.sweep.cells import (
    CELL_FILE,
    LOG_FILE,
    cell_state,
    error_line,
    evaluate_command,
    stream_command,
)
from lolgps_torch.sweep.grid import (
    Cell,
    Outcome,
    Plan,
    Sweep,
    build_parser,
    make_grid,
    make_sweep,
    parse_seeds,
    split_extra,
)
from lolgps_torch.sweep.run import Progress, format_duration, main
from lolgps_torch.sweep.summary import (
    aggregate,
    cell_metrics,
    format_mean_sd,
    mean_sd,
    write_summaries,
)

__all__ = [
    "CELL_FILE",
    "LOG_FILE",
    "Cell",
    "Outcome",
    "Plan",
    "Progress",
    "Sweep",
    "aggregate",
    "build_parser",
    "cell_metrics",
    "cell_state",
    "error_line",
    "evaluate_command",
    "format_duration",
    "format_mean_sd",
    "main",
    "make_grid",
    "make_sweep",
    "mean_sd",
    "parse_seeds",
    "split_extra",
    "stream_command",
    "write_summaries",
]
