"""Where the placement puts the hole and the start pose, per arm and seed of the default stream.

    python scripts/research/placements.py --urdf URDF [URDF ...] [--seeds 0 1 2 3 4]

For each arm and seed: the nominal hole mouth (m, world frame) and the start pose q0 (rad)
that ``run_stream.py --urdf URDF --seed S`` would use, or the one-line refusal. Run it on two
commits and compare the outputs (``diff``) to see which arms a change to the placement moves.
"""

from __future__ import annotations

import argparse
import warnings

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import PlacementConfig, place_task
from lolgps_torch.task import TaskConfig, load_task_arm


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", nargs="+", required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    args = parser.parse_args()
    for urdf in args.urdf:
        task = TaskConfig(urdf=urdf)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arm = load_task_arm(task)
        kinematics = PegKinematics(arm, "cpu")
        for seed in args.seeds:
            conditions, _ = default_training_stream(AreaConfig(), seed)
            try:
                config = PlacementConfig(positions=tuple(conditions))
                geometry = place_task(arm, kinematics, config, task.world.depth)
                mouth = " ".join(f"{v:.4f}" for v in geometry.nominal_mouth)
                q0 = " ".join(f"{v:.3f}" for v in geometry.q0)
                print(f"{urdf} seed {seed}: mouth {mouth} q0 {q0}", flush=True)
            except LolgpsError as error:
                print(f"{urdf} seed {seed}: refused: {error}", flush=True)


if __name__ == "__main__":
    run(main)
