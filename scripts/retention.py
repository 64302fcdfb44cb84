"""Plot a run's retention curve: each training position's policy distance after every S-step.

    python scripts/retention.py --run DIR

Loads the policy checkpointed after each condition and rolls it out without noise at every
training position of the run, and measures its action error on each position's D_g (in the
teacher p_cur's standard deviations). Writes DIR/retention.json (two tables, row = the policy
after condition k, column = training position j) and DIR/retention.png, and prints the
distances with the positions forgotten: succeeded right after their own S-step, missed at the
end. Works on an interrupted run (the conditions completed so far).
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import write_json
from lolgps_torch.evaluation.retention import forgotten, plot_retention, retention
from lolgps_torch.lolgps.run import load_run


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    args = parser.parse_args()
    loaded = load_run(args.run)
    table = retention(loaded)
    folder = loaded.folder.path
    write_json(folder / "retention.json", table)
    plot_retention(table, folder / "retention.png", f"{folder.name}: retention")
    threshold = table["success_threshold"]
    print("policy final distance (mm) after the S-step of condition k (rows), per position")
    print("k   " + " ".join(f"{c:>7d}" for c in table["conditions"]))
    for k, row in zip(table["conditions"], table["distance"], strict=True):
        cells = " ".join(f"{d * 1000:6.1f}{'*' if d < threshold else ' '}" for d in row)
        print(f"{k:<3d} {cells}")
    print(f"* = success (< {threshold * 1000:.0f} mm); forgotten: {forgotten(table) or 'none'}")
    print(f"wrote {folder / 'retention.json'} and {folder / 'retention.png'}")


if __name__ == "__main__":
    run(main)
