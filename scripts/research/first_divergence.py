"""Where two runs of the same stream part: the first iteration whose record differs, and
whether their summaries agree.

    python scripts/research/first_divergence.py RUN_A RUN_B [--check]

Reads both runs' ``metrics.jsonl`` and prints the first iteration (condition, iteration) at
which the two records differ in anything but their timings, with the relative difference of
their mean sample costs; or that they never differ. Where both runs have a ``summary.json``,
it then compares them, timings aside (any key starting with ``time``), and prints the first
field that differs or that they are identical. With ``--check`` the script exits with status 1
when anything differs: the check that a change which should not alter behaviour (a refactor, a
move of code) leaves the default stream on seed 0 as it was (``CONTRIBUTING.md``).

Two runs whose code computes the same arithmetic in another order (the same S-step up to
rounding) agree exactly until the first rollouts whose actions the rounding touched, and from
there are two draws of the same learning: the closed loop with contact amplifies a difference
of 1e-13 in an action to one in the outcome.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder


def untimed(value: Any) -> Any:
    """``value`` without the keys that start with ``time``, at every depth."""
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items() if not k.startswith("time")}
    if isinstance(value, list):
        return [untimed(v) for v in value]
    return value


def first_difference(a: Any, b: Any, where: str = "") -> str | None:
    """The path of the first place where ``a`` and ``b`` differ, with both values; None if
    they are equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                return f"{where}.{key}: present in one summary only"
            found = first_difference(a[key], b[key], f"{where}.{key}")
            if found:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{where}: {len(a)} entries against {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            found = first_difference(x, y, f"{where}[{i}]")
            if found:
                return found
        return None
    return None if a == b else f"{where}: {a!r} against {b!r}"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs=2, help="two finished or partial run folders")
    parser.add_argument(
        "--check", action="store_true", help="exit with status 1 when the runs differ"
    )
    args = parser.parse_args()
    first, second = args.runs
    differ = False
    iterations = [
        [
            untimed(r)
            for r in RunFolder(path).read_metrics()
            if "iteration" in r and "event" not in r
        ]
        for path in (first, second)
    ]
    for a, b in zip(*iterations, strict=False):
        if a != b:
            gap = abs(a["mean_cost"] - b["mean_cost"]) / abs(b["mean_cost"])
            print(
                f"first difference: condition {a['condition']}, iteration {a['iteration']} "
                f"(against condition {b['condition']}, iteration {b['iteration']}); mean cost "
                f"{a['mean_cost']:.6g} against {b['mean_cost']:.6g}, relative difference {gap:.2g}"
            )
            differ = True
            break
    else:
        print(f"the first {min(map(len, iterations))} iteration records are identical")
        differ = len(iterations[0]) != len(iterations[1])
    summaries = [Path(path) / "summary.json" for path in (first, second)]
    if all(path.exists() for path in summaries):
        a, b = (untimed(json.loads(path.read_text())) for path in summaries)
        found = first_difference(a, b, "summary")
        print(f"first summary difference: {found}" if found else "the summaries are identical")
        differ = differ or found is not None
    if args.check and differ:
        sys.exit(1)


if __name__ == "__main__":
    run(main)
