"""Run a grid of seeds x methods x arms x streams (x variants) of run_stream.py on Ray, and
aggregate it.

    python scripts/sweep.py --seeds 0-2 --methods lolgps naive batch \\
        --urdf robots/kuka_peg.urdf other.urdf --stream paper --out runs/sweep1 \\
        [--conditions FILE] [--variants FILE] [--evaluate] [--address ADDR] [--num-cpus N] \\
        [-- run_stream flags]

One folder per cell under --out (``<method>-<urdf stem>-<stream>[-<variant>]-seed<S>``; a
``--variants`` file names run_stream flag sets, ``{"gmm": "--dynamics-prior gmm", ...}``, and
each cell runs once per set), each a complete run_stream run (with eval.json when
--evaluate); sweep.json records the grid, and summary.md, summary.csv and summary.png
aggregate the seeds (mean ± sd). Without --address a local Ray
instance with --num-cpus CPUs (default: all) runs the cells, one CPU each; --address auto
joins a running cluster. Rerunning the same command skips finished cells and resumes
interrupted ones. A failed cell is retried once; the exit status is 1 if any finally failed.
Needs Ray: pip install -e '.[ray]'.
"""

from __future__ import annotations

import sys
from pathlib import Path

from lolgps_torch import sweep
from lolgps_torch.cli import run


def main() -> None:
    """Run the sweep on this command line; exit 1 if a cell failed."""
    status = sweep.main(sys.argv[1:], scripts=str(Path(__file__).resolve().parent))
    if status:
        sys.exit(status)


if __name__ == "__main__":
    run(main)
