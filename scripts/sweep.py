"""Run a grid of stream runs on Ray and aggregate it: the ``lolgps sweep`` command (``--help``
tells all)."""

import sys

from lolgps_torch.cli import run
from lolgps_torch.sweep import main

if __name__ == "__main__":
    run(lambda: sys.exit(main()))
