"""Where two runs of the same stream part: the first iteration whose record differs.

    python scripts/research/first_divergence.py RUN_A RUN_B

Reads both runs' ``metrics.jsonl`` and prints the first iteration (condition, iteration) at
which the two records differ in anything but their timings, with the relative difference of
their mean sample costs; or that they never differ. Two runs whose code computes the same
arithmetic in another order (the same S-step up to rounding) agree exactly until the first
rollouts whose actions the rounding touched, and from there are two draws of the same learning:
the closed loop with contact amplifies a difference of 1e-13 in an action to one in the
outcome.
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs=2, help="two finished or partial run folders")
    first, second = parser.parse_args().runs
    iterations = [
        [
            {k: v for k, v in r.items() if not k.startswith("time")}
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
            return
    print(f"the first {min(map(len, iterations))} iteration records are identical")


if __name__ == "__main__":
    run(main)
