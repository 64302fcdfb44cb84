"""Trace a run's global policy step by step at its training positions, to see how it misses.

    python scripts/trace_policy.py --run DIR [--checkpoint N] [--steps 0 3 6 10 20 50 99]
                                   [--area-misses K]

For each condition in DIR/replay.h5 it prints two lines:

- ``rollout``: the tip's error ``p_tip - p*_tip`` (mm; x, y, z with z up) at the chosen steps of
  the policy's noiseless rollout there, and the final distance (m). A peg stopped on the plate
  beside the mouth of the 0.10 m deep hole shows as z near +100 mm with a lateral error.
- ``D_g fit``: at the same steps, the policy's action error on the condition's stored
  successful states, averaged over samples: relative, ``|mu_theta(x) - mu_cur(x)| / |mu_cur(x)|``,
  and in p_cur's standard deviations, ``sqrt(d^T P_cur d)`` with ``d = mu_theta(x) - mu_cur(x)``
  (the S-step's own measure), where ``mu_cur``, ``P_cur`` are the stored distillation targets.
  It tells an under-fitted S-step (large on D_g) from a policy that fits D_g but drifts off it.

``--checkpoint`` picks the policy saved after that condition (default: the last).

``--area-misses K`` instead traces the test positions of area K in DIR/eval.json (written by
``scripts/evaluate.py``) that the last stage's policy missed, with their distance to the
nearest training position: one ``rollout`` line each, no D_g fit.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import checkpoint_dir, read_run
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.task import PegTask, TaskConfig, task_config_from_dict


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="run folder (config.json, replay.h5)")
    parser.add_argument("--checkpoint", type=int, default=None, help="policy after condition N")
    parser.add_argument(
        "--steps", type=int, nargs="+", default=[0, 3, 6, 10, 20, 50, 99], help="steps to print"
    )
    parser.add_argument(
        "--area-misses",
        type=int,
        default=None,
        metavar="K",
        help="trace test area K's positions the final policy missed (from DIR/eval.json)",
    )
    args = parser.parse_args()
    info = read_run(args.run)
    task_config = task_config_from_dict(info.task)
    T = task_config.world.T
    bad = [t for t in args.steps if not 0 <= t < T]
    if bad:
        raise LolgpsError(f"--steps must lie in [0, {T}), got {bad}")
    if args.area_misses is not None:
        trace_area_misses(args.run, task_config, args.area_misses, args.steps)
        return
    replay = ReplayBuffer(Path(args.run) / "replay.h5")
    records = [replay.read_condition(i) for i in replay.conditions()]
    if not records:
        raise LolgpsError(f"{args.run}/replay.h5 holds no conditions")
    last = records[-1].condition if args.checkpoint is None else args.checkpoint
    policy = GaussianPolicy.load(checkpoint_dir(args.run, last))
    errors, finals = _tip_errors(task_config, policy, [r.offset for r in records], args.steps)
    steps = torch.tensor(args.steps)
    print(f"policy after condition {last}; columns: steps {args.steps}")
    for i, record in enumerate(records):
        print(
            f"condition {record.condition} ({record.offset[0]:+.3f}, {record.offset[1]:+.3f}) "
            f"rollout tip error mm {_cells(errors[i])} final {finals[i]:.3f} m"
        )
        samples = record.samples
        if samples.x.shape[0] == 0:
            print("    D_g fit: no stored successes")
            continue
        with torch.no_grad():
            mean = policy(samples.x[:, steps])
        diff = mean - samples.mean_cur[:, steps]
        relative = (diff.norm(dim=-1) / samples.mean_cur[:, steps].norm(dim=-1)).mean(0)
        prec = samples.prec_cur[:, steps]
        sigmas = (diff.unsqueeze(-2) @ prec @ diff.unsqueeze(-1)).flatten(-3).sqrt().mean(0)
        print(
            "    D_g fit: |mu_theta - mu_cur| / |mu_cur| "
            + " ".join(f"{v:.2f}" for v in relative)
            + "; in p_cur's standard deviations "
            + " ".join(f"{v:.1f}" for v in sigmas)
        )


def _tip_errors(
    task_config: TaskConfig,
    policy: GaussianPolicy,
    offsets: list[tuple[float, float]],
    steps: list[int],
) -> tuple[torch.Tensor, list[float]]:
    """The policy's noiseless rollouts at ``offsets``: the tip error ``p_tip - p*_tip`` (mm)
    at ``steps``, ``[len(offsets), len(steps), 3]``, and the final distances (m)."""
    task = PegTask(task_config, n_worlds=5)
    rollouts = task.sample(policy_actor(policy), offsets)
    task.close()
    tip = task.layout.points.start
    errors = rollouts.x[:, torch.tensor(steps), tip : tip + 3] * 1000.0
    return errors, rollouts.final_distance.tolist()


def _cells(error_mm: torch.Tensor) -> str:
    return " ".join(f"({e[0]:+.0f},{e[1]:+.0f},{e[2]:+.0f})" for e in error_mm.tolist())


def trace_area_misses(run_dir: str, task_config: TaskConfig, area: int, steps: list[int]) -> None:
    """Rollout lines at the positions of test area ``area`` that the last stage missed."""
    try:
        evaluation = json.loads((Path(run_dir) / "eval.json").read_text())
        stage = evaluation["stages"][-1]
        group = evaluation["groups"][area]
        finals = stage["per_position"]["final_distance"][area]
        threshold = float(evaluation["success_threshold"])
        training = evaluation["training"]["conditions"]
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise LolgpsError(f"{run_dir}/eval.json: no test area {area} to trace ({exc})") from None
    misses = [tuple(p) for p, d in zip(group["positions"], finals, strict=True) if d >= threshold]
    print(f"{stage['name']} policy, {group['label']}: {len(misses)}/{len(finals)} missed")
    if not misses:
        return
    policy = GaussianPolicy.load(Path(run_dir) / stage["checkpoint"])
    errors, final = _tip_errors(task_config, policy, misses, steps)
    print(f"columns: steps {steps}")
    for i, (dx, dy) in enumerate(misses):
        nearest = min(math.dist((dx, dy), t) for t in training) * 1000.0
        print(
            f"({dx:+.3f}, {dy:+.3f}), {nearest:.0f} mm from a training position: rollout tip "
            f"error mm {_cells(errors[i])} final {final[i]:.3f} m"
        )


if __name__ == "__main__":
    run(main)
