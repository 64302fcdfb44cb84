"""How fast the global policy moves the arm, step by step, against the speeds its data held then.

    python scripts/research/speed_envelope.py RUN_OR_SWEEP ... [--windows 0 5 10]
                                              [--margins 1.5 2 3] [--floors 0 0.1] [--onward]

For every evaluated run (a sweep folder stands for every evaluated run in it), the last stage's
policy is rolled out, as it acts (guard included), at every test position of eval.json. Each
rollout's joint speeds are compared with D_g's per-step envelope

    E_j(t) = max(max_{m, |s - t| <= w} |q-dot_j^m(s)|, f max_{m, s} |q-dot_j^m(s)|)

over every condition's stored rollouts ``m`` (window ``w`` steps, floor ``f`` of the largest
speed; ``--onward``: over ``s >= t - w``, the largest speed D_g still reaches from then on), by ``r(t) = max_j |q-dot_j(t)| / E_j(t)``. For each (w, f, margin) it prints how many
successful rollouts would have passed ``margin`` (a brake tripping there would cost them), how
many misses pass it and when, and the tip's distance from its hole at that step, next to the
rollout's final distance: whether a time-varying trip would stop a flung arm near the hole,
or whether the guard's one speed for every step (the largest in D_g) is all the data allows.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from itertools import product

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.run_folder import evaluated_runs
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import read_evaluation
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import policy_actor


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", help="evaluated run folders or sweep folders")
    parser.add_argument("--windows", type=int, nargs="+", default=[0, 5, 10])
    parser.add_argument("--margins", type=float, nargs="+", default=[1.5, 2.0, 3.0])
    parser.add_argument("--floors", type=float, nargs="+", default=[0.0, 0.1])
    parser.add_argument("--onward", action="store_true", help="windows reach to the last step")
    args = parser.parse_args()
    if min(args.windows) < 0 or min(args.margins) <= 0 or min(args.floors) < 0:
        raise LolgpsError("windows and floors must be >= 0 and margins > 0")
    return args


def envelope(speeds: torch.Tensor, window: int, floor: float, onward: bool) -> torch.Tensor:
    """``E_j(t)`` of D_g's joint speeds ``speeds: [M, T, n]`` (module docstring), ``[T, n]``."""
    per_step = speeds.abs().amax(0)  # [T, n]
    T = per_step.shape[0]
    windowed = torch.stack(
        [per_step[max(0, t - window) : T if onward else t + window + 1].amax(0) for t in range(T)]
    )
    return torch.maximum(windowed, floor * per_step.amax(0))


def measure(path: str, args: argparse.Namespace, table: dict[tuple, list[list[float]]]) -> None:
    """Roll out ``path``'s last policy at its test positions and add, per (w, f, margin), one
    ``[success, tripped, trip step, distance at trip, final distance]`` row per rollout."""
    loaded = load_run(path)
    evaluation = read_evaluation(loaded.folder.path)
    stage = evaluation["stages"][-1]
    threshold = float(evaluation["success_threshold"])
    positions = [tuple(p) for g in evaluation["groups"] for p in g["positions"]]
    policy = load_policy(loaded.folder.path / stage["checkpoint"])
    task = loaded.make_task()
    try:
        rollouts = task.sample(policy_actor(policy, task.model), positions)
    finally:
        task.close()
    qd, points = task.layout.qd, task.layout.points
    data = torch.cat([r.samples.x[..., qd] for r in loaded.records if r.samples.x.shape[0]])
    speeds = rollouts.x[..., qd].abs()  # [N, T, n]
    distance = rollouts.x[..., points.start : points.start + 3].norm(dim=-1)  # [N, T]
    final = rollouts.final_distance
    success = final < threshold
    for w, f in product(args.windows, args.floors):
        ratio = (speeds / envelope(data, w, f, args.onward)).amax(-1)  # [N, T]
        for m in args.margins:
            over = ratio > m
            tripped = over.any(-1)
            step = torch.where(tripped, over.float().argmax(-1), torch.full_like(final, -1).long())
            at = distance.gather(1, step.clamp(min=0)[:, None])[:, 0]
            for i in range(rollouts.N):
                table[(w, f, m)].append(
                    [float(success[i]), float(tripped[i]), float(step[i]), float(at[i]),
                     float(final[i])]
                )  # fmt: skip
    print(f"{path}: {rollouts.N} test rollouts, {int(success.sum())} successes")


def report(table: dict[tuple, list[list[float]]]) -> None:
    print(
        "| window | floor | margin | successes tripped | misses tripped | misses > 0.3 m "
        "tripped | median trip step (misses > 0.3 m) | largest distance at trip (misses > 0.3 m) "
        "| trip steps of successes |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for (w, f, m), rows in table.items():
        data = torch.tensor(rows)
        success, tripped, step, at, final = data.unbind(-1)
        hit, miss = success > 0, success == 0
        far = miss & (final > 0.3)
        far_tripped = far & (tripped > 0)
        median = step[far_tripped].median().item() if far_tripped.any() else float("nan")
        largest = at[far_tripped].max().item() if far_tripped.any() else float("nan")
        print(
            f"| {w} | {f} | {m} | {int((tripped[hit] > 0).sum())}/{int(hit.sum())} | "
            f"{int((tripped[miss] > 0).sum())}/{int(miss.sum())} | "
            f"{int(far_tripped.sum())}/{int(far.sum())} | {median:.0f} | {largest:.3f} | "
            f"{_quartiles(step[hit & (tripped > 0)])} |"
        )


def _quartiles(steps: torch.Tensor) -> str:
    """Lowest, quartiles and highest of ``steps`` (``-`` for none)."""
    if steps.numel() == 0:
        return "-"
    q = torch.quantile(steps, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0]))
    return " / ".join(f"{v:.0f}" for v in q.tolist())


def main() -> None:
    args = parse_args()
    table: dict[tuple, list[list[float]]] = defaultdict(list)
    for folder in args.folders:
        for path in evaluated_runs(folder):
            measure(str(path), args, table)
    report(table)


if __name__ == "__main__":
    run(main)
