"""Learn a stream of conditions with LOLGPS: the ``lolgps run`` command (``--help`` tells all)."""

from lolgps_torch.cli import run
from lolgps_torch.commands.run import main

if __name__ == "__main__":
    run(main)
