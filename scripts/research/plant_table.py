"""The robustness table: the stream on plants that depart from the URDF, per learner.

    python scripts/research/plant_table.py variants [--plants P ...] [--priors L ...] > FILE
    python scripts/sweep.py --seeds 0-2 --urdf robots/kuka_peg.urdf PANDA.urdf \\
        --variants FILE --out DIR
    python scripts/research/plant_table.py table DIR [DIR ...]

``variants`` prints a ``--variants`` file for ``scripts/sweep.py``: one flag set per plant
(:data:`PLANTS`, the simulated arm's departure from the URDF, ``PlantConfig``; by default the
seven of :data:`TABLE`, the others harsher: 0.5 and 2 kg, inertia and payload without any
compensation, a delay between control steps with noise) and learner
(:data:`PRIORS`: the URDF's fixed model as the dynamics prior, the arm identified from its
rollouts, or the sample-only GMM prior, by default; or the GMM prior from the hold rather than
a controller planned on the model), named ``<plant>.<learner>``. ``table`` reads the
finished cells of such sweeps (merged: a seed's run counted once) and prints a
markdown table, a row per arm, plant and learner (in that order): the positions the final
policy inserts the peg at (per seed), the worst final distance of a local controller over the
seeds, and the means over seeds of the rollouts, of the first
iteration with a successful sample (over the conditions) and of the S-step's repair rounds;
with ``--identify``, the payload identified after the first condition and the one-step
joint-speed errors of the identified model and of the true arm's on the second condition's
first rollouts (``metrics.jsonl``, event ``identified``).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path
from typing import Any

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder, read_json
from lolgps_torch.errors import LolgpsError

# name: (label, run_stream flags)
PLANTS = {
    "urdf": ("the URDF", ""),
    "inertia": ("inertia ±30 %", "--plant-inertia-scale 0.3 --plant-seed 1"),
    "payload": ("+1 kg, compensated by the URDF", "--payload 1 --gravity-compensation model"),
    "nocomp": ("no gravity compensation", "--gravity-compensation none"),
    "noise": ("sensor noise 1 mrad", "--obs-noise 0.001"),
    "late10": ("commands 10 ms late", "--action-delay 0.01"),
    "late50": ("commands 50 ms late", "--action-delay 0.05"),
    "payload05": ("+0.5 kg, compensated by the URDF", "--payload 0.5 --gravity-compensation model"),
    "payload2": ("+2 kg, compensated by the URDF", "--payload 2 --gravity-compensation model"),
    "combo": (
        "inertia ±30 %, +1.5 kg, no compensation",
        "--plant-inertia-scale 0.3 --plant-seed 7 --payload 1.5 --gravity-compensation none",
    ),
    "late35noise": ("commands 35 ms late, 1 mrad noise", "--action-delay 0.035 --obs-noise 0.001"),
}
TABLE = ("urdf", "inertia", "payload", "nocomp", "noise", "late10", "late50")  # the default set
PRIORS = {
    "model": ("URDF model", ""),
    "identified": ("identified", "--identify"),
    "gmm": ("GMM", "--dynamics-prior gmm"),
    "gmmhold": ("GMM from the hold", "--dynamics-prior gmm --model-plans 0"),
}


def variants(plants: list[str], priors: list[str]) -> dict[str, str]:
    """The ``--variants`` object: ``<plant>.<prior>`` to its run_stream flags."""
    return {
        f"{plant}.{prior}": f"{PLANTS[plant][1]} {PRIORS[prior][1]}".strip()
        for plant in plants
        for prior in priors
    }


def identified_after_first(folder: Path) -> tuple[float, float, float] | None:
    """The payload identified after the first condition and the one-step errors (rad/s) of the
    identified model and of the true arm's, None if the run did not identify."""
    path = RunFolder(folder).metrics_path
    if not path.is_file():
        return None
    for line in path.read_text().splitlines():
        record = json.loads(line)
        if record.get("event") == "identified" and record["condition"] == 1:
            plant = record.get("error_plant")
            return (
                float(record["payload"]),
                float(record["error_identified"]),
                math.nan if plant is None else float(plant),
            )
    return None


def cell_row(folder: Path) -> dict[str, Any] | None:
    """One finished run's numbers, None if it has not finished."""
    run_folder = RunFolder(folder)
    if not run_folder.summary_path.is_file():
        return None
    entries = run_folder.read_summary()["conditions"]
    firsts = [e["first_success_iteration"] for e in entries]
    return {
        "positions": sum(bool(e["policy_success_end"]) for e in entries),
        "conditions": len(entries),
        "worst": max(float(e["local_final_distance"]) for e in entries),
        "rollouts": sum(int(e["rollouts"]) for e in entries),
        "first": statistics.fmean(math.inf if f is None else f for f in firsts),
        "repairs": sum(int(e.get("repairs") or 0) for e in entries),
        "identified": identified_after_first(folder),
    }


def table(folders: list[Path]) -> str:
    """The markdown table of the sweeps in ``folders`` (their sweep.json's cells)."""
    groups: dict[tuple[str, str], dict[int, dict[str, Any]]] = {}  # a run per seed
    for out in folders:
        if not (out / "sweep.json").is_file():
            raise LolgpsError(f"{out}: no sweep.json (not a sweep folder)")
        for cell in read_json(out / "sweep.json")["cells"]:
            plant, _, prior = cell["variant"].partition(".")
            if plant not in PLANTS or prior not in PRIORS:
                raise LolgpsError(f"{out}: variant {cell['variant']!r} is not <plant>.<prior>")
            row = cell_row(out / cell["name"])
            group = groups.setdefault((cell["arm"], cell["variant"]), {})
            if row is not None:
                group.setdefault(int(cell["seed"]), row)  # a seed in two folders counts once
    lines = [
        "| arm | plant | learner | seeds | positions | worst p_cur (m) | rollouts | "
        "first success (iteration) | repair rounds | after condition 1: payload (kg), "
        "one-step error identified / true arm's (rad/s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    arms = list(dict.fromkeys(arm for arm, _ in groups))

    def order(key: tuple[str, str]) -> tuple[int, int, int]:
        plant, _, prior = key[1].partition(".")
        return arms.index(key[0]), list(PLANTS).index(plant), list(PRIORS).index(prior)

    for (arm, variant), seeds in sorted(groups.items(), key=lambda item: order(item[0])):
        rows = [seeds[seed] for seed in sorted(seeds)]
        if not rows:
            continue
        plant, _, prior = variant.partition(".")
        identified = [r["identified"] for r in rows if r["identified"] is not None]
        found = "; ".join(f"{p:.3f}, {e:.4f} / {t:.4f}" for p, e, t in identified) or "–"
        positions = ", ".join(f"{r['positions']}/{r['conditions']}" for r in rows)
        lines.append(
            f"| {arm} | {PLANTS[plant][0]} | {PRIORS[prior][0]} | {len(rows)} | {positions} | "
            f"{max(r['worst'] for r in rows):.3f} | "
            f"{statistics.fmean(r['rollouts'] for r in rows):.0f} | "
            f"{statistics.fmean(r['first'] for r in rows):.1f} | "
            f"{statistics.fmean(r['repairs'] for r in rows):.1f} | {found} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    write = commands.add_parser("variants", help="print a sweep --variants file")
    write.add_argument("--plants", nargs="+", choices=list(PLANTS), default=list(TABLE))
    write.add_argument(
        "--priors", nargs="+", choices=list(PRIORS), default=["model", "identified", "gmm"]
    )
    read = commands.add_parser("table", help="the markdown table of a finished sweep")
    read.add_argument("out", nargs="+", help="sweep folders (holding sweep.json)")
    args = parser.parse_args()
    if args.command == "variants":
        json.dump(variants(args.plants, args.priors), sys.stdout, indent=1)
        print()
        return
    print(table([Path(out) for out in args.out]), end="")


if __name__ == "__main__":
    run(main)
