"""Export a run folder's trajectories as an HDF5 or a Minari dataset (schema: datasets/README.md).

    python scripts/export_dataset.py --run runs/lolgps-seed0 --out datasets/lolgps-seed0.h5
    python scripts/export_dataset.py --run runs/lolgps-seed0 --format minari \\
        --out ~/.minari/datasets/peg-insertion-lolgps-v0

For --format minari, --out is the dataset folder: its name is the Minari dataset id (NAME-vN)
and its parent the datasets root, so ``MINARI_DATASETS_PATH=<parent>`` and
``minari.load_dataset("<name>")`` open it, and its ``recover_environment()`` rebuilds the run's
task. The arm is read from the run folder's copy of its URDF; runs made before runs kept one
name it by the path they were given: export those from the folder the run was started in.
An existing output is kept unless --force. On a terminal, progress bars show on stderr.
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.data import export_hdf5, export_minari


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder made by scripts/run_stream.py")
    parser.add_argument(
        "--out", required=True, help="HDF5 file, or Minari dataset folder <root>/<NAME-vN>"
    )
    parser.add_argument("--format", choices=("hdf5", "minari"), default="hdf5")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    export = export_minari if args.format == "minari" else export_hdf5
    report = export(args.run, args.out, force=args.force)
    print(
        f"wrote {report.path}: {report.trajectories} trajectories, {report.steps} steps, "
        f"{report.megabytes:.1f} MB in {report.seconds:.1f} s"
    )


if __name__ == "__main__":
    run(main)
