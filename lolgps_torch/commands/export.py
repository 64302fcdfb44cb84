"""Export a run folder's trajectories as an HDF5, a Minari or a LeRobot dataset (schema:
datasets/README.md).

    lolgps export --run runs/lolgps-seed0 --out datasets/lolgps-seed0.h5
    lolgps export --run runs/lolgps-seed0 --format minari \\
        --out ~/.minari/datasets/peg-insertion-lolgps-v0
    lolgps export --run runs/lolgps-seed0 --format lerobot \\
        --out datasets/lolgps-seed0-lerobot [--video] [--size W H] [--view wide|mouth]

For --format minari, --out is the dataset folder: its name is the Minari dataset id (NAME-vN)
and its parent the datasets root, so ``MINARI_DATASETS_PATH=<parent>`` and
``minari.load_dataset("<name>")`` open it, and its ``recover_environment()`` rebuilds the run's
task. For --format lerobot, --out is the dataset folder, which LeRobot's
``LeRobotDataset(<any repo id>, root=<out>)`` reads: one episode per successful trajectory,
its frames at 1/dt per second, its task the hole's offset; --video adds each episode's camera
stream, the arm filmed from its recorded joint angles as render.py films it (a fixed camera
per episode, no captions; needs the ``video`` extra). The arm is read from the run folder's
copy of its URDF; runs made before runs kept one name it by the path they were given: export
those from the folder the run was started in. An existing output is kept unless --force. On a
terminal, progress bars show on stderr.

The same command: ``python scripts/export_dataset.py``.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from lolgps_torch.data import export_hdf5, export_minari
from lolgps_torch.data.dataset import RunData
from lolgps_torch.data.export_lerobot import Film, export_lerobot
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.render import RenderConfig, check_output, write_video
from lolgps_torch.evaluation.scene import Scene
from lolgps_torch.progress import progress
from lolgps_torch.task import load_task_arm


def parse_args(argv: Sequence[str] | None, prog: str | None) -> argparse.Namespace:
    """The command line ``argv`` parsed, ``prog`` the command's name in the usage."""
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder made by scripts/run_stream.py")
    parser.add_argument(
        "--out",
        required=True,
        help="HDF5 file, Minari dataset folder <root>/<NAME-vN>, or LeRobot dataset folder",
    )
    parser.add_argument("--format", choices=("hdf5", "minari", "lerobot"), default="hdf5")
    parser.add_argument(
        "--video", action="store_true", help="lerobot: add each episode's camera stream"
    )
    defaults = RenderConfig()
    parser.add_argument(
        "--size", type=int, nargs=2, default=list(defaults.size), metavar=("W", "H"),
        help=f"--video: frame width and height (pixels, even; default {defaults.size})",
    )  # fmt: skip
    parser.add_argument(
        "--view", choices=("wide", "mouth"), default=defaults.view, help="--video: the camera"
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")
    return parser.parse_args(argv)


def camera(config: RenderConfig) -> Film:
    """Film a run's episodes through the display scene of render.py: each episode from its
    own fixed camera (``config``'s view and size), one frame per state ``x_0 .. x_{T-1}``."""
    width, height = config.size

    def film(run_data: RunData, rows: Sequence[int], path: Path, fps: int) -> tuple[int, int]:
        task = run_data.task
        arm = load_task_arm(task)
        mouth = tuple(run_data.meta["arm"]["nominal_hole_mouth"])
        scene = Scene(arm, task.world, mouth, config.view)
        tr = run_data.trajectories
        q, T = task.world.layout(arm.dof).q, tr.cost.shape[1]

        def frames() -> Iterator[np.ndarray]:
            for row in progress(rows, len(rows), "filming"):
                offset = (float(tr.hole_offset[row, 0]), float(tr.hole_offset[row, 1]))
                angles = tr.states[row, :T, q].numpy()
                fixed = scene.camera(offset, angles[0])
                for t in range(T):
                    scene.show(offset, angles[t])
                    yield scene.photograph(fixed, width, height)[0]

        try:
            write_video(frames(), path, fps)
        finally:
            scene.close()
        return width, height

    return film


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Export the run the command line ``argv`` (default: this process's) names."""
    args = parse_args(argv, prog)
    if args.video and args.format != "lerobot":
        raise LolgpsError(f"--video goes with --format lerobot, not {args.format}")
    if args.format == "lerobot":
        film = None
        if args.video:
            config = RenderConfig(view=args.view, size=tuple(args.size))
            check_output(Path(args.out) / "video.mp4")  # an .mp4 needs the video extra
            film = camera(config)
        report = export_lerobot(args.run, args.out, force=args.force, film=film)
    else:
        export = export_minari if args.format == "minari" else export_hdf5
        report = export(args.run, args.out, force=args.force)
    print(
        f"wrote {report.path}: {report.trajectories} trajectories, {report.steps} steps, "
        f"{report.megabytes:.1f} MB in {report.seconds:.1f} s"
    )
