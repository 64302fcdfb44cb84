"""Film a run's noiseless rollouts at its training positions: the ``lolgps render`` command (``--help`` tells all)."""

from lolgps_torch.cli import run
from lolgps_torch.commands.render import main

if __name__ == "__main__":
    run(main)
