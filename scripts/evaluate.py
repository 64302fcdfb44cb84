"""Evaluate a run's global policies on the test areas: the ``lolgps evaluate`` command (``--help`` tells all)."""

from lolgps_torch.cli import run
from lolgps_torch.commands.evaluate import main

if __name__ == "__main__":
    run(main)
