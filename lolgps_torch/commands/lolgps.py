"""The ``lolgps`` command (also ``python -m lolgps_torch``): ``lolgps COMMAND [FLAGS]``, each
command taking exactly the flags of its script in the repository's ``scripts/``, and
``lolgps COMMAND --help`` telling all of it."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError

# command -> (its module, whose main(argv, prog) runs it; what it does, as the usage says)
COMMANDS = {
    "run": ("lolgps_torch.commands.run", "learn a stream of hole positions"),
    "evaluate": ("lolgps_torch.commands.evaluate", "a run's policies on the test areas"),
    "sweep": ("lolgps_torch.sweep.run", "a grid of runs on Ray, and its aggregate"),
    "export": ("lolgps_torch.commands.export", "a run's trajectories as a dataset"),
    "render": ("lolgps_torch.commands.render", "a video of a run's noiseless rollouts"),
    "report": ("lolgps_torch.commands.report", "a run's report.html"),
}


def usage() -> str:
    """The command's usage: its commands, one line each."""
    lines = [f"  {name:<9} {job}" for name, (_, job) in COMMANDS.items()]
    return "usage: lolgps COMMAND [FLAGS]  (lolgps COMMAND --help)\n\ncommands:\n" + "\n".join(
        lines
    )


def dispatch(argv: Sequence[str]) -> None:
    """Run the command ``argv`` names with the rest of ``argv``; ``--help`` prints the usage;
    a command's non-zero status ends this process with it."""
    if argv and argv[0] in ("-h", "--help"):
        print(usage())
        return
    if not argv:
        raise LolgpsError(f"expected a command, one of {', '.join(COMMANDS)} (see --help)")
    name, *flags = argv
    if name not in COMMANDS:
        raise LolgpsError(f"unknown command {name!r}: choose from {', '.join(COMMANDS)}")
    status = importlib.import_module(COMMANDS[name][0]).main(flags, prog=f"lolgps {name}")
    if status:
        sys.exit(status)


def main(argv: Sequence[str] | None = None) -> None:
    """The ``lolgps`` console command: :func:`dispatch` of ``argv`` (default: this process's
    arguments), bad input one ``error:`` line and exit status 2."""
    run(lambda: dispatch(sys.argv[1:] if argv is None else argv))
