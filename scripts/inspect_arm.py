"""Print what lolgps_torch understood of a URDF arm, and check its kinematics against PyBullet.

python scripts/inspect_arm.py --urdf robots/kuka_peg.urdf [--ee-link NAME]
python scripts/inspect_arm.py --mjcf robot.xml --sim mujoco [--ee-link BODY_OR_SITE]
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from lolgps_torch.cli import add_task_arguments, run, task_config
from lolgps_torch.robot.placement import reach
from lolgps_torch.task import PegTask


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser)
    parser.add_argument("--checks", type=int, default=5, help="random poses for the FK check")
    args = parser.parse_args()
    task = PegTask(task_config(args), n_worlds=1)
    arm = task.arm
    kind = "MJCF" if task.config.mjcf else "URDF"
    print(f"{kind}          {arm.source_path}  (sha256 {arm.source_sha256[:12]})")
    print(f"root link     {arm.root_link}")
    print(f"base link     {arm.base_link}  (the arm's chain starts here; --base-link)")
    print(f"end effector  {arm.ee_link}")
    peg = "carried by the URDF" if arm.peg_link != "lolgps_peg" else "attached by lolgps_torch"
    print(f"peg           link {arm.peg_link} ({peg}), radius {arm.peg_radius:.4f} m")
    print(
        f"peg points    tip {arm.point_offsets[0]}, top {arm.point_offsets[1]} in {arm.point_link}"
    )
    print(
        f"\n{'joint':<24}{'lower':>9}{'upper':>9}{'effort':>9}{'vel':>8}{'q0':>9}   (deg, N m, rad/s)"
    )
    for i, name in enumerate(arm.joint_names):
        print(
            f"{name:<24}{math.degrees(arm.lower[i]):9.1f}{math.degrees(arm.upper[i]):9.1f}"
            f"{arm.effort[i]:9.1f}{arm.velocity[i]:8.2f}{math.degrees(task.geometry.q0[i]):9.1f}"
        )
    if arm.held:
        print("\nheld fixed    (above the base link, off the chain, mimic or prismatic; --hold)")
        for name, value in arm.held:
            print(f"  {name:<24}{value:9.4g}")
    lay = task.layout
    print(f"\nstate layout  dX = {lay.dX}, dU = {lay.dU}")
    for block, (start, stop) in lay.as_dict().items():
        print(f"  x[{start}:{stop}]  {block}")
    mouth = task.geometry.nominal_mouth
    _, radius = reach(task.arm, task.kinematics)
    print(f"\nreach         {radius:.3f} m from the shoulder to the peg tip")
    print(f"nominal hole  mouth at ({mouth[0]:.3f}, {mouth[1]:.3f}, {mouth[2]:.3f}) m")

    world = task.sampler.worlds[0]
    rng = np.random.default_rng(0)
    lo, hi = np.array(arm.lower), np.array(arm.upper)
    worst: float = 0.0
    for _ in range(args.checks):
        pose = lo + (hi - lo) * rng.random(arm.dof)
        world.reset(pose)
        fk = task.kinematics.points(torch.tensor(pose)).numpy()
        worst = max(worst, float(np.abs(fk - world.points()).max()))
    verdict = "OK" if worst < 1e-6 else "MISMATCH"
    print(
        f"FK check      {args.checks} random poses, max |pytorch-kinematics - {task.config.sim}| = {worst:.2e} m  {verdict}"
    )
    task.close()


if __name__ == "__main__":
    run(main)
