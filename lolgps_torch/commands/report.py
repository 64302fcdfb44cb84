"""Write a run's report: DIR/report.html, one page that opens offline in a browser.

    lolgps report --run DIR [--no-make]

The page shows the configuration, the per-condition table, the Fig. 4 evaluation (fig4.png,
made by scripts/evaluate.py), the retention curve and every video in DIR/videos/, linked by
paths relative to DIR. Unless --no-make, the retention curve (as scripts/retention.py makes
it) and a video of the final policy at every training position (as scripts/render.py makes
it: DIR/videos/policy-wide.mp4, or .gif without the video extra) are made first where
missing; the evaluation takes minutes and is left to scripts/evaluate.py.

The same command: ``python scripts/report.py``.
"""

from __future__ import annotations

import argparse
import importlib.util
from collections.abc import Sequence
from pathlib import Path

from lolgps_torch.data.run_folder import RunFolder, write_json
from lolgps_torch.evaluation.render import RenderConfig, render_run
from lolgps_torch.evaluation.report import (
    RETENTION_FIGURE,
    RETENTION_FILE,
    VIDEO_DIR,
    videos,
    write_report,
)
from lolgps_torch.evaluation.retention import plot_retention, retention
from lolgps_torch.lolgps.run import load_run


def make_missing(path: Path) -> None:
    """The retention curve and the default video, where the run folder has none."""
    if (path / RETENTION_FIGURE).is_file() and videos(path):
        return
    loaded = load_run(path)
    if not (path / RETENTION_FIGURE).is_file():
        table = retention(loaded)
        write_json(path / RETENTION_FILE, table)
        plot_retention(table, path / RETENTION_FIGURE, f"{path.name}: retention")
        print(f"wrote {path / RETENTION_FIGURE}")
    if not videos(path):
        suffix = ".mp4" if importlib.util.find_spec("imageio_ffmpeg") else ".gif"
        out = path / VIDEO_DIR / f"policy-wide{suffix}"
        render_run(loaded, [r.condition for r in loaded.records], RenderConfig(), out)
        print(f"wrote {out}")


def main(argv: Sequence[str] | None = None, prog: str | None = None) -> None:
    """Write the report of the run the command line ``argv`` (default: this process's) names."""
    parser = argparse.ArgumentParser(
        prog=prog, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json)")
    parser.add_argument(
        "--no-make",
        dest="make",
        action="store_false",
        help="only assemble what the folder holds (make no retention curve or video)",
    )
    args = parser.parse_args(argv)
    folder = RunFolder(args.run)
    folder.read_config()  # a missing or corrupt run is an error before any work
    if args.make:
        make_missing(folder.path)
    print(f"wrote {write_report(folder.path)}")
