"""Write a run's report.html: the ``lolgps report`` command (``--help`` tells all)."""

from lolgps_torch.cli import run
from lolgps_torch.commands.report import main

if __name__ == "__main__":
    run(main)
