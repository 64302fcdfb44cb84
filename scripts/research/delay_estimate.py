"""How well the command delay is found from excitation rollouts: the estimate against the plant's
true delay, for each arm, delay, sensor noise, payload and gravity compensation given.

    python scripts/research/delay_estimate.py --urdf robots/kuka_peg.urdf \\
        --delays 0 0.01 0.025 0.04 0.05 0.06 0.075 0.1 --obs-noise 0 0.001 \\
        --payloads 0 0.5 1 2 --gravity-compensation plant model --seeds 0 1 \\
        [--rollouts 8 --steps 40] [--speed 0.05]

Prints one line per plant: the true and estimated delay (physics steps and s), how much larger
the residual of the next best candidate's fit is (the margin, ``lolgps_torch/sim/latency.py``),
and that of the fit with no delay (how badly a model that takes each command at once explains
the arm); then how many estimates are right: the plant's delay in whole physics steps, or
either whole step around a delay between two. ``--seeds`` sets both the plant's seed (its
sensor noise) and the excitation's; ``--rollouts`` and ``--steps`` shape the excitation and
``--speed`` sizes it (default: the learner's, ``DelayConfig``). The plant is read here only to
set the simulated arm.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from typing import get_args

from lolgps_torch.arm_probes import fit_scale, measure_delay
from lolgps_torch.cli import run
from lolgps_torch.sim.latency import DelayConfig
from lolgps_torch.sim.plant import GravityCompensation, PlantConfig
from lolgps_torch.task import TaskConfig


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
    parser.add_argument(
        "--payloads", type=float, nargs="+", default=[0.0], help="plant payloads (kg)"
    )
    parser.add_argument(
        "--gravity-compensation",
        nargs="+",
        default=["plant"],
        choices=get_args(GravityCompensation),
        help="plant gravity compensations",
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="plant seeds")
    parser.add_argument("--rollouts", type=int, default=DelayConfig.rollouts)
    parser.add_argument("--steps", type=int, default=DelayConfig.steps)
    parser.add_argument(
        "--speed", type=float, default=DelayConfig.speed, help="excitation (rad/s per step)"
    )
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    plants = [
        PlantConfig(action_delay=d, obs_noise=s, payload=m, gravity_compensation=g, seed=k)
        for g in args.gravity_compensation
        for m in args.payloads
        for s in args.obs_noise
        for k in args.seeds
        for d in args.delays
    ]
    for plant in plants:  # every setting checked before any work
        TaskConfig(urdf=args.urdf, plant=plant)
    settings = DelayConfig(rollouts=args.rollouts, steps=args.steps, speed=args.speed)
    base, _ = fit_scale(TaskConfig(urdf=args.urdf))
    right = 0
    for plant in plants:
        start = time.perf_counter()
        estimate = measure_delay(replace(base, plant=plant), replace(settings, seed=plant.seed))
        margin = sorted(estimate.relative_rss)[1]
        whole, fraction = plant.delay_steps(base.world.dt / base.world.substeps)
        right += estimate.steps in ((whole, whole + 1) if fraction else (whole,))
        print(
            f"delay {plant.action_delay:.3f} s, noise {plant.obs_noise:g}, payload "
            f"{plant.payload:g} kg, compensation {plant.gravity_compensation}, seed {plant.seed}: "
            f"estimated {estimate.seconds:.3f} s ({estimate.steps} physics steps), next fit's "
            f"residual x{margin:.3g}, no delay's x{estimate.relative_rss[0]:.3g}, "
            f"{time.perf_counter() - start:.1f} s"
        )
    print(f"{right} of {len(plants)} estimates right")


if __name__ == "__main__":
    run(main)
