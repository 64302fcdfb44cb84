"""Trace a run's global policy step by step at its training positions, to see how it misses.

    python scripts/research/trace_policy.py --run DIR [--checkpoint N]
                                            [--steps 0 3 6 10 20 50 99] [--area-misses K]
                                            [--stage NAME]

For each condition in DIR/replay.h5 it prints two lines:

- ``rollout``: the tip's error ``p_tip - p*_tip`` (mm; x, y, z with z up) at the chosen steps of
  the policy's noiseless rollout there, and the final distance (m). A peg stopped on the plate
  beside the mouth of the 0.10 m deep hole shows as z near +100 mm with a lateral error.
- ``D_g fit``: at the same steps, the policy's action error on the condition's stored
  successful states, averaged over samples: relative, ``|mu_theta(x) - mu_cur(x)| / |mu_cur(x)|``,
  and in p_cur's standard deviations, ``sqrt(d^T P_cur d)`` with ``d = mu_theta(x) - mu_cur(x)``
  (the S-step's own measure), where ``mu_cur``, ``P_cur`` are the stored distillation targets.
  It tells an under-fitted S-step (large on D_g) from a policy that fits D_g but drifts off it.

- ``support``: at the same steps, how far the rollout's state is from the nearest training
  condition's support, ``min_m g_t(x)`` in D_g(m)'s standard deviations (the gate of the
  S-step's visited states, :mod:`lolgps_torch.lolgps.onpolicy`), and over the whole rollout
  the peak joint speed over the joint's velocity limit and the peak torque over the largest
  torque in every D_g. It tells a policy that leaves its data early from one that drifts late,
  and shows what the arm does where it misses.

``--checkpoint`` picks the policy saved after that condition (default: the last).

``--area-misses K`` instead traces the test positions of area K in DIR/eval.json (written by
``scripts/evaluate.py``) that the last stage's policy (``--stage NAME``: that stage's) missed, with their distance to the
nearest training position: a ``rollout`` and a ``support`` line each, no D_g fit.
"""

from __future__ import annotations

import argparse
import math

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.evaluate import read_evaluation
from lolgps_torch.evaluation.retention import fit_error
from lolgps_torch.lolgps.onpolicy import Teacher, support_distance
from lolgps_torch.lolgps.run import LoadedRun, load_run
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.state import StateLayout
from lolgps_torch.types import Trajectories


def parse_args() -> argparse.Namespace:
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
    parser.add_argument(
        "--stage", default=None, help="with --area-misses: the stage's policy (default: the last)"
    )
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    loaded = load_run(args.run)
    T = loaded.info.task.world.T
    bad = [t for t in args.steps if not 0 <= t < T]
    if bad:
        raise LolgpsError(f"--steps must lie in [0, {T}), got {bad}")
    if args.area_misses is not None:
        trace_area_misses(loaded, args.area_misses, args.steps, args.stage)
        return
    last = loaded.records[-1].condition if args.checkpoint is None else args.checkpoint
    policy = loaded.policy(last)
    offsets = [r.offset for r in loaded.records]
    rollouts, speeds = _rollouts(loaded, policy, offsets)
    errors, finals = _tip_errors(rollouts, args.steps), rollouts.final_distance.tolist()
    support = _support_lines(loaded, rollouts, speeds, args.steps)
    print(f"policy after condition {last}; columns: steps {args.steps}")
    for i, record in enumerate(loaded.records):
        print(
            f"condition {record.condition} ({record.offset[0]:+.3f}, {record.offset[1]:+.3f}) "
            f"rollout tip error mm {_cells(errors[i])} final {finals[i]:.3f} m"
        )
        print("    " + support[i])
        samples = record.samples
        if samples.x.shape[0] == 0:
            print("    D_g fit: no stored successes")
            continue
        print(
            "    D_g fit: "
            + _fit_line(policy, samples.x, samples.mean_cur, samples.prec_cur, args.steps)
        )


def _fit_line(
    policy: GaussianPolicy,
    x: torch.Tensor,
    mean_cur: torch.Tensor,
    prec_cur: torch.Tensor,
    steps: list[int],
) -> str:
    """The policy's action error on stored states ``x: [M, T, dX]`` against p_cur's means
    ``[M, T, dU]`` and precisions ``[M, T, dU, dU]`` at ``steps``, averaged over samples:
    relative, and in p_cur's standard deviations."""
    at = torch.tensor(steps)
    with torch.no_grad():
        diff = policy(x[:, at]) - mean_cur[:, at]
    relative = (diff.norm(dim=-1) / mean_cur[:, at].norm(dim=-1)).mean(0)
    sigmas = fit_error(policy, x[:, at], mean_cur[:, at], prec_cur[:, at]).mean(0)
    return (
        "|mu_theta - mu_cur| / |mu_cur| "
        + " ".join(f"{v:.2f}" for v in relative)
        + "; in p_cur's standard deviations "
        + " ".join(f"{v:.1f}" for v in sigmas)
    )


def _rollouts(
    loaded: LoadedRun, policy: GaussianPolicy, offsets: list[tuple[float, float]]
) -> tuple[Trajectories, torch.Tensor]:
    """The policy's noiseless rollouts at ``offsets``, and each one's peak joint speed over
    the joint's velocity limit ``[len(offsets)]``."""
    task = loaded.make_task()
    try:
        rollouts = task.sample(policy_actor(policy, task.model), offsets)
    finally:
        task.close()
    limits = torch.tensor(task.arm.velocity, dtype=torch.float64)
    speeds = (rollouts.x[..., task.layout.qd].abs() / limits).amax(dim=(1, 2))
    return rollouts, speeds


def _tip_errors(rollouts: Trajectories, steps: list[int]) -> torch.Tensor:
    """The tip error ``p_tip - p*_tip`` (mm) of ``rollouts`` at ``steps``,
    ``[N, len(steps), 3]``."""
    tip = StateLayout((rollouts.x.shape[-1] - 12) // 2).points.start
    return rollouts.x[:, torch.tensor(steps), tip : tip + 3] * 1000.0


def _support_lines(
    loaded: LoadedRun, rollouts: Trajectories, speeds: torch.Tensor, steps: list[int]
) -> list[str]:
    """Per rollout: its distance to the nearest training condition's support at ``steps``
    (D_g standard deviations), its peak speed over the limits and its peak torque over the
    largest in every D_g."""
    n = (rollouts.x.shape[-1] - 12) // 2
    layout = StateLayout(n)
    stream = loaded.info.stream
    floor = torch.zeros(layout.dX, dtype=torch.float64)
    floor[layout.q], floor[layout.qd] = stream.onpolicy_floor, 10.0 * stream.onpolicy_floor
    kept = [r for r in loaded.records if r.samples.x.shape[0] > 0]
    nearest = torch.stack(
        [
            support_distance(rollouts.x, Teacher.of(r.condition, r.offset, r.samples.x, None),
                             layout, floor)
            for r in kept
        ]
    ).amin(0)  # fmt: skip
    largest = torch.cat([r.samples.u.abs().flatten(0, 1) for r in kept]).amax(0)  # [dU]
    torque = (rollouts.u.abs() / largest).amax(dim=(1, 2))
    at = torch.tensor(steps)
    return [
        "support (sd) "
        + " ".join(f"{v:.1f}" for v in nearest[i, at].tolist())
        + f"; peak speed {speeds[i]:.2f} of the limit, peak torque {torque[i]:.2f} of D_g's"
        for i in range(rollouts.N)
    ]


def _cells(error_mm: torch.Tensor) -> str:
    return " ".join(f"({e[0]:+.0f},{e[1]:+.0f},{e[2]:+.0f})" for e in error_mm.tolist())


def trace_area_misses(
    loaded: LoadedRun, area: int, steps: list[int], stage_name: str | None
) -> None:
    """Rollout lines at the positions of test area ``area`` that the stage ``stage_name``
    (None: the last) missed."""
    folder: RunFolder = loaded.folder
    try:
        evaluation = read_evaluation(folder.path)
        stages = {s["name"]: s for s in evaluation["stages"]}
        stage = evaluation["stages"][-1] if stage_name is None else stages[stage_name]
        group = evaluation["groups"][area]
        finals = stage["per_position"]["final_distance"][area]
        threshold = float(evaluation["success_threshold"])
        training = evaluation["training"]["conditions"]
    except (LolgpsError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise LolgpsError(f"{folder.eval_path}: no test area {area} to trace ({exc})") from None
    misses = [tuple(p) for p, d in zip(group["positions"], finals, strict=True) if d >= threshold]
    print(f"{stage['name']} policy, {group['label']}: {len(misses)}/{len(finals)} missed")
    if not misses:
        return
    policy = load_policy(folder.path / stage["checkpoint"])
    rollouts, speeds = _rollouts(loaded, policy, misses)
    errors, final = _tip_errors(rollouts, steps), rollouts.final_distance.tolist()
    support = _support_lines(loaded, rollouts, speeds, steps)
    print(f"columns: steps {steps}")
    for i, (dx, dy) in enumerate(misses):
        nearest = min(math.dist((dx, dy), t) for t in training) * 1000.0
        print(
            f"({dx:+.3f}, {dy:+.3f}), {nearest:.0f} mm from a training position: rollout tip "
            f"error mm {_cells(errors[i])} final {final[i]:.3f} m"
        )
        print("    " + support[i])


if __name__ == "__main__":
    run(main)
