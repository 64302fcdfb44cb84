"""Markdown tables for docs/RESULTS.md from finished runs (summary.json, and eval.json if any).

    python scripts/research/summarize_results.py runs/lolgps-seed0 runs/lolgps-seed1 runs/naive-seed0 ...

Prints: the global policy alone at the training positions (per run), and, from eval.json,
the success rate and mean final distance per stage and test area averaged over the seeds of
each method, with the forgetting and the average final success.
"""

from __future__ import annotations

import argparse
import statistics
from collections import defaultdict
from dataclasses import asdict
from typing import Any

from lolgps_torch.cli import run
from lolgps_torch.cost.l12 import CostConfig
from lolgps_torch.data.run_folder import RunFolder, as_stored, flatten
from lolgps_torch.evaluation.evaluate import read_evaluation
from lolgps_torch.lolgps import StreamConfig, method_config
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.simulator import WorldConfig

PER_RUN = {"seed", "policy.seed"}  # settings every seed changes


def _mean_sd(values: list[float]) -> str:
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.2f}"
    return f"{statistics.mean(values):.2f} ± {statistics.stdev(values):.2f}"


def label(folder: str) -> str:
    """The method, with its alpha setting for LOLGPS and every stream, cost and world setting
    that differs from the method's defaults (ablations share the method name); settings of
    earlier versions show as they were saved."""
    config = RunFolder(folder).read_config()
    method = str(config["method"])
    sections = {
        "": (config["stream"], as_stored(asdict(method_config(method, StreamConfig())))),
        "cost.": (config["task"]["cost"], asdict(CostConfig())),
        "world.": (config["task"]["world"], asdict(WorldConfig())),
        "plant.": (config["task"].get("plant", {}), asdict(PlantConfig())),
    }
    extras = []
    for prefix, (saved, default) in sections.items():
        mine, defaults = flatten(saved), flatten(default)
        extras += [
            f"{prefix}{key} {value}"
            for key, value in mine.items()
            if f"{prefix}{key}" not in PER_RUN and value != defaults.get(key)
        ]
    if method == "lolgps":
        stream = config["stream"]
        extras.insert(0, f"alpha {stream['alpha']:g} {stream['alpha_schedule']}")
    return f"{method} ({', '.join(extras)})" if extras else method


def training_table(runs: list[str]) -> None:
    print(
        "| run | method | seed | policy succeeds at training positions (end) | per condition: final distance after its S-step → at the end (m) |"
    )
    print("|---|---|---|---|---|")
    for folder in runs:
        s = RunFolder(folder).read_summary()
        entries = s["conditions"]
        solved = sum(bool(e["policy_success_end"]) for e in entries)
        cells = ", ".join(
            f"{e['policy_final_distance_after']:.3f}→{e['policy_final_distance_end']:.3f}"
            for e in entries
        )
        print(f"| {folder} | {label(folder)} | {s['seed']} | {solved}/{len(entries)} | {cells} |")


def local_table(runs: list[str]) -> None:
    """Per run: positions the final policy inserts at, the local controllers' worst final
    distance and how many succeeded, the rollouts and the conditions that failed."""
    print("| run | settings | policy (end) | worst p_cur (m) | p_cur succeeds | rollouts |")
    print("|---|---|---|---|---|---|")
    for folder in runs:
        entries = RunFolder(folder).read_summary()["conditions"]
        solved = sum(bool(e["policy_success_end"]) for e in entries)
        worst = max(e["local_final_distance"] for e in entries)
        local = sum(bool(e["local_success"]) for e in entries)
        rollouts = sum(e["rollouts"] for e in entries)
        print(
            f"| {folder} | {label(folder)} | {solved}/{len(entries)} | {worst:.3f} | "
            f"{local}/{len(entries)} | {rollouts} |"
        )


def eval_tables(runs: list[str]) -> None:
    done = [f for f in runs if RunFolder(f).eval_path.exists()]
    if not done:
        return
    evals = [read_evaluation(f) for f in done]
    by_method: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for folder, e in zip(done, evals, strict=True):
        by_method[label(folder)].append(e)
    print(
        "\nSuccess rate per test area (mean ± sd over seeds; area k is centred 0.05·k m from the nominal hole):\n"
    )
    n_areas = len(evals[0]["stages"][-1]["groups"])
    print("| method | seeds | stage | " + " | ".join(f"area {k}" for k in range(n_areas)) + " |")
    print("|---|---|---|" + "---|" * n_areas)
    for method, items in by_method.items():
        names = [st["name"] for st in items[0]["stages"]]
        for i, name in enumerate(names):
            cells = [
                _mean_sd(
                    [
                        e["stages"][i]["groups"][k]["success_rate"]["mean"]
                        for e in items
                        if i < len(e["stages"])
                    ]
                )
                for k in range(n_areas)
            ]
            print(f"| {method} | {len(items)} | {name} | " + " | ".join(cells) + " |")
    print("\nMean final tip distance per test area (m, mean over seeds):\n")
    print("| method | stage | " + " | ".join(f"area {k}" for k in range(n_areas)) + " |")
    print("|---|---|" + "---|" * n_areas)
    for method, items in by_method.items():
        for i, st in enumerate(items[0]["stages"]):
            cells = [
                f"{statistics.mean(e['stages'][i]['groups'][k]['final_distance']['mean'] for e in items):.3f}"
                for k in range(n_areas)
            ]
            print(f"| {method} | {st['name']} | " + " | ".join(cells) + " |")
    forgetting_table(by_method)


def forgetting_table(by_method: dict[str, list[dict[str, Any]]]) -> None:
    """The forgetting of success on areas 0 and 2 and the average final success per method,
    mean ± sd over its seeds' evaluations."""
    print(
        "\n| method | seeds | forgetting of success, area 0 (points) | forgetting of success, area 2 (points) | average final success |"
    )
    print("|---|---|---|---|---|")
    for method, items in by_method.items():

        def forgot(area: int, group: list[dict[str, Any]] = items) -> str:
            vals = []
            for e in group:
                f = e["metrics"].get("forgetting")
                if f and f["success_rate"]["per_area"][area] is not None:
                    vals.append(100 * f["success_rate"]["per_area"][area])
            return _mean_sd(vals)

        final = _mean_sd([e["metrics"]["average_final_success"] for e in items])
        print(f"| {method} | {len(items)} | {forgot(0)} | {forgot(2)} | {final} |")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders")
    parser.add_argument(
        "--local",
        action="store_true",
        help="instead: the local controllers' worst distance and successes and the rollouts",
    )
    args = parser.parse_args()
    if args.local:
        local_table(args.runs)
        return
    training_table(args.runs)
    eval_tables(args.runs)


if __name__ == "__main__":
    run(main)
