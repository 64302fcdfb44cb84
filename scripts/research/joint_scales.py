"""What resists each joint of an arm over the exploration noise's correlation time: its
inertia or its damping.

    python scripts/research/joint_scales.py --urdf URDF [URDF ...]

Per actuated joint at the start pose: the effective inertia ``m = 1 / (M(q0)^-1)_jj``
(kg m^2, PyBullet's mass matrix), the URDF damping b (N m s/rad, as PyBullet applies it), and
``b tau / m`` with ``tau = noise_smoothing dt`` of the default local learner: above 1 the
damping, not the inertia, decides how far the initial controller's noise moves the joint.
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.task import PegTask, TaskConfig


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", nargs="+", required=True)
    args = parser.parse_args()
    for urdf in args.urdf:
        task = PegTask(TaskConfig(urdf=urdf), n_worlds=1)
        try:
            tau = LocalConfig().noise_smoothing * task.config.world.dt
            m, b = task.effective_inertia(), task.joint_damping()
            print(f"{urdf} (tau = {tau:.2f} s)")
            print("  m (kg m^2)  " + " ".join(f"{v:8.3f}" for v in m.tolist()))
            print("  b (N m s)   " + " ".join(f"{v:8.2f}" for v in b.tolist()))
            print("  b tau / m   " + " ".join(f"{v:8.1f}" for v in (b * tau / m).tolist()))
        finally:
            task.close()


if __name__ == "__main__":
    run(main)
