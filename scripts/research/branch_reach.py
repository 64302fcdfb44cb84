"""Can the arm reach each hole of a finished run from the start pose it ran with?

    python scripts/research/branch_reach.py RUN [RUN ...]

The start pose and the hole the run used are read from its stored samples (the first state's
joint angles, and its peg points minus their offsets from the targets), not recomputed, so a
run made before a change of the placement is measured as it ran. For every condition it
follows the hole floor from the start pose continuously (:func:`follow`, as the placement
does) and prints the point error at the end (mm), the least dexterity on the way as a
fraction of the arm's reach per radian, beside the run's outcome there: its local
controller's final distance and the final policy's (m).
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.run import read_run
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import follow, generic_rank, reach, vertical_peg_targets
from lolgps_torch.state import StateLayout
from lolgps_torch.task import load_task_arm


def table(path: str) -> list[str]:
    """One Markdown row per condition of the run at ``path``."""
    folder = RunFolder(path)
    info = read_run(folder)
    task = info.task
    arm = load_task_arm(task)
    kin = PegKinematics(arm, "cpu")
    lay = StateLayout(arm.dof)
    replay = ReplayBuffer(folder.replay_path)
    used = next(
        (
            (i, samples.x[0, 0])
            for i in replay.conditions()
            if (samples := replay.read_condition(i, torch.device("cpu")).samples).x.shape[0]
        ),
        None,
    )
    if used is None:
        raise LolgpsError(f"{path}: no stored sample to read the start pose from")
    index, x0 = used
    q0 = x0[lay.q]
    offset = torch.tensor([*info.conditions[index], -task.world.depth], dtype=torch.float64)
    tip_target = kin.points(q0)[0] - x0[lay.points][:3]
    mouth = tip_target - offset
    floors = mouth + torch.nn.functional.pad(
        torch.tensor(info.conditions, dtype=torch.float64), (0, 1), value=-task.world.depth
    )
    holes = vertical_peg_targets(floors, -arm.point_offsets[1][2])
    _, radius = reach(arm, kin)
    lo = torch.tensor(arm.lower, dtype=torch.float64)
    hi = torch.tensor(arm.upper, dtype=torch.float64)
    generic = lo + (hi - lo) * torch.rand(64, arm.dof, generator=torch.Generator().manual_seed(0))
    rank = generic_rank(kin, generic.to(torch.float64))
    error, least = follow(kin, arm, q0, holes, rank)
    summary = folder.read_summary()["conditions"]
    rows = []
    for c, (dx, dy) in enumerate(info.conditions):
        done = summary[c] if c < len(summary) else {}
        rows.append(
            f"| {path} | {c} | ({dx:+.3f}, {dy:+.3f}) | {1000 * float(error[c]):.1f} "
            f"| {float(least[c]) / radius:.4f} | {done.get('local_final_distance', float('nan')):.4f} "
            f"| {done.get('policy_final_distance_end', float('nan')):.4f} |"
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="finished run folders")
    args = parser.parse_args()
    print(
        "| run | condition | offset (m) | followed: error (mm) | least dexterity (reach/rad) "
        "| local final (m) | policy final (m) |"
    )
    print("|---|---|---|---|---|---|---|")
    for path in args.runs:
        print("\n".join(table(path)))


if __name__ == "__main__":
    run(main)
