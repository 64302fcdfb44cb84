"""Export a run folder's trajectories as a dataset: the ``lolgps export`` command (``--help`` tells all)."""

from lolgps_torch.cli import run
from lolgps_torch.commands.export import main

if __name__ == "__main__":
    run(main)
