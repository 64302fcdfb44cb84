"""How fast a run's rollouts move the arm against its URDF's velocity limits, and when.

    python scripts/research/speed_limits.py RUN_OR_SWEEP ... [--steps 6]

For every run (a sweep folder stands for every run in it), each condition's stored rollouts in
D_g (``replay.h5``) are compared with the arm's velocity limits by ``r(t) = max_j |q-dot_j(t)|
/ v_j``. It prints, per run: how many rollouts pass a limit (``max_t r(t) > 1``), the median and
largest peak ``max_t r(t)``, the control step at which the peak comes (the most common), the mean
``r(t)`` over rollouts at each of the first ``--steps`` steps and over the rest, and the first
command's size ``max_j |u_j(0)| / effort_j``. Where the run was evaluated (``eval.json``), it adds
the policy's test rollouts over a limit, their largest peak and their faults, per stage.
"""

from __future__ import annotations

import argparse
import statistics
from collections import Counter
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import EVAL_FILE
from lolgps_torch.evaluation.evaluate import read_evaluation
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.task import load_task_arm


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders or sweep folders")
    parser.add_argument("--steps", type=int, default=6, help="first steps shown one by one")
    return parser.parse_args()


def run_folders(paths: list[str]) -> list[Path]:
    """Every run folder (one with a replay) at or below ``paths``."""
    found: list[Path] = []
    for path in map(Path, paths):
        found.extend(sorted(p.parent for p in path.rglob("replay.h5")))
    return found


def teachers(path: Path, steps: int) -> str:
    """One line on D_g's rollouts of the run at ``path`` (module docstring)."""
    loaded = load_run(path)
    arm = load_task_arm(loaded.info.task)
    velocity = torch.tensor(arm.velocity, dtype=torch.float64)
    effort = torch.tensor(arm.effort, dtype=torch.float64)
    layout = loaded.info.task.world.layout(arm.dof)
    ratios, first = [], []
    for record in loaded.records:
        x, u = record.samples.x, record.samples.u
        ratios.append((x[..., layout.qd].abs() / velocity).amax(-1))  # [N, T]
        first.append((u[:, 0].abs() / effort).amax(-1))
    r = torch.cat(ratios)
    peaks, when = r.max(-1)
    profile = " ".join(f"{v:.2f}" for v in r[:, :steps].mean(0).tolist())
    step, _ = Counter(when.tolist()).most_common(1)[0]
    return (
        f"{path.name}: D_g {int((peaks > 1).sum())}/{len(peaks)} over a limit, peak median "
        f"{peaks.median():.2f} max {peaks.max():.2f} (most often at step {step}); mean r(t) "
        f"t<{steps}: {profile}, after: {r[:, steps:].mean():.2f}; first command "
        f"{statistics.median(torch.cat(first).tolist()):.2f} of effort (median)"
    )


def evaluated(path: Path) -> list[str]:
    """Per evaluated stage of the run at ``path``: test rollouts over a limit, the largest
    peak and the faults (nothing for a run never evaluated)."""
    if not (path / EVAL_FILE).is_file():
        return []
    lines = []
    for stage in read_evaluation(path)["stages"]:
        speeds = [v for group in stage["per_position"]["peak_speed"] for v in group]
        faults = sum(sum(group) for group in stage["per_position"].get("fault", []))
        lines.append(
            f"  {stage['name']}: {sum(v > 1 for v in speeds)}/{len(speeds)} test rollouts over "
            f"a limit, largest {max(speeds):.2f}, faults {faults}"
        )
    return lines


def main() -> None:
    args = parse_args()
    for path in run_folders(args.runs):
        print(teachers(path, args.steps))
        for line in evaluated(path):
            print(line)


if __name__ == "__main__":
    run(main)
