"""How well the command delay is found from excitation rollouts: the estimate against the plant's
true delay, for each arm, delay and sensor noise given.

    python scripts/research/delay_estimate.py --urdf robots/kuka_peg.urdf \\
        --delays 0 0.01 0.02 0.03 0.04 0.05 --obs-noise 0 0.001

Prints one line per (delay, noise): the true and estimated delay (physics steps and s), and
how much larger the residual of the next best candidate's fit is (the margin,
``lolgps_torch/sim/latency.py``), and that of the fit with no delay (how badly a model that
takes each command at once explains the arm). The plant is read here only to set the simulated arm.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from lolgps_torch.cli import run
from lolgps_torch.sim.latency import DelayConfig
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.task import TaskConfig, fit_scale, measure_delay


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf", help="the arm's URDF file")
    parser.add_argument(
        "--delays",
        type=float,
        nargs="+",
        default=[0.0, 0.01, 0.02, 0.05],
        help="plant delays (s)",
    )
    parser.add_argument(
        "--obs-noise", type=float, nargs="+", default=[0.0], help="plant sensor noise levels (rad)"
    )
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    plants = [PlantConfig(action_delay=d, obs_noise=s) for s in args.obs_noise for d in args.delays]
    for plant in plants:  # every plant checked before any work
        TaskConfig(urdf=args.urdf, plant=plant)
    base, _ = fit_scale(TaskConfig(urdf=args.urdf))
    for plant in plants:
        start = time.perf_counter()
        estimate = measure_delay(replace(base, plant=plant), DelayConfig())
        margin = sorted(estimate.relative_rss)[1]
        print(
            f"delay {plant.action_delay:.3f} s, noise {plant.obs_noise:g}: estimated "
            f"{estimate.seconds:.3f} s ({estimate.steps} physics steps), next fit's residual "
            f"x{margin:.3g}, no delay's x{estimate.relative_rss[0]:.3g}, "
            f"{time.perf_counter() - start:.1f} s"
        )


if __name__ == "__main__":
    run(main)
