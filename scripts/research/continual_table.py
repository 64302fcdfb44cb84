"""One row per finished run: its rollouts and its continual-learning metrics.

    python scripts/research/continual_table.py RUN [RUN ...]

Columns, from each run's summary.json and, if ``scripts/evaluate.py --run RUN --scratch auto``
has been run, its eval.json: the global policy at the training positions at the end; the
rollouts in all, at conditions 0-3 and at 4-7 and their ratio; Continual World's forward
transfer, mean over conditions 1-7 and over 4-7; success on test areas 0, 2 and 4 after the
last stage (on the square stream's test set, ``evaluate.py --square``, its one group); the
forgetting of area 0 (points of success lost between the stage that trained it and the last).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.evaluation.evaluate import read_evaluation
from lolgps_torch.evaluation.table import markdown_table


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return sum(kept) / len(kept) if kept else None


def _text(value: float | None, form: str) -> str:
    return "-" if value is None else format(value, form)


def row(path: Path) -> list[str]:
    """The table's cells for the run at ``path``."""
    folder = RunFolder(path)
    summary = folder.read_summary()
    conditions = summary["conditions"]
    reached = sum(bool(c.get("policy_success_end")) for c in conditions)
    rollouts = [int(c["rollouts"]) for c in conditions]
    early, late = sum(rollouts[:4]), sum(rollouts[4:])
    cells = [
        path.name,
        f"{reached}/{len(conditions)}",
        f"{sum(rollouts)}",
        f"{early} / {late} ({late / early:.2f})",
    ]
    if folder.eval_path.exists():
        data: dict[str, Any] = read_evaluation(path)
        metrics = data["metrics"]
        ft = [r["forward_transfer"] for r in metrics.get("forward_transfer") or []]
        last = data["stages"][-1]["groups"]
        areas = [last[k]["success_rate"]["mean"] for k in (0, 2, 4) if k < len(last)]
        forgetting = metrics["forgetting"]  # None for other test sets than the areas
        lost = forgetting["success_rate"]["per_area"][0] if forgetting else None
        cells += [
            _text(_mean(ft[1:]), ".2f"),
            _text(_mean(ft[4:]), ".2f"),
            " / ".join(f"{100 * a:.0f}" for a in areas),
            _text(None if lost is None else 100 * lost, "+.0f"),
        ]
    else:
        cells += ["-"] * 4
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    args = parser.parse_args()
    header = (
        "run", "policy", "rollouts", "conditions 0-3 / 4-7", "FT 1-7", "FT 4-7",
        "areas 0 / 2 / 4 (%)", "forgetting, area 0 (points)",
    )  # fmt: skip
    print(markdown_table(header, (row(path) for path in args.runs)))


if __name__ == "__main__":
    run(main)
