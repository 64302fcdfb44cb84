"""How many excitation rollouts the command delay's estimate needs (each is a reset of the arm).

    python scripts/research/delay_rollouts.py [--urdf URDF ...] [--shapes 128x5 32x5 16x10 ...]
                                              [--seeds 0 1 2 3]

For every arm (default: the KUKA and pybullet_data's Panda, each placed as a stream places it)
and every excitation shape ``R x S`` (R rollouts of S control steps from rest at the start
pose, :class:`~lolgps_torch.sim.latency.DelayConfig`), the delay is estimated
(:func:`~lolgps_torch.arm_probes.measure_delay`) on plants with delays of 0 to 70 ms, with
sensor noise (1 and 2 mrad, at every ``--seeds`` noise seed, which also seeds the commands),
and under payloads that only the URDF's gravity compensation holds. It prints, per arm and
shape, the estimates that miss the plant's delay, and the smallest margin of a right estimate:
the second smallest residual over the smallest (1: a tie, no delay is told apart).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from lolgps_torch.arm_probes import fit_scale, measure_delay
from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.sim.latency import DelayConfig
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.task import TaskConfig

ROOT = Path(__file__).resolve().parents[2]


def plants(seeds: list[int]) -> list[PlantConfig]:
    """The plants each shape is tried on: the delays of the latency tests, sensor noise at
    every seed, and payloads held by the URDF's compensation alone."""
    delays = [PlantConfig(action_delay=d) for d in (0.0, 0.01, 0.02, 0.03, 0.05, 0.07)]
    noisy = [
        PlantConfig(action_delay=d, obs_noise=n, seed=s)
        for s in seeds
        for d, n in ((0.0, 0.001), (0.0, 0.002), (0.05, 0.001), (0.02, 0.001))
    ]
    loads = [
        PlantConfig(payload=1.0, gravity_compensation="model", inertia_scale=0.3),
        PlantConfig(payload=2.0, gravity_compensation="model", action_delay=0.05),
        PlantConfig(payload=0.5, gravity_compensation="model", action_delay=0.02),
    ]
    return delays + noisy + loads


def shape(text: str) -> tuple[int, int]:
    try:
        rollouts, steps = (int(v) for v in text.split("x"))
    except ValueError:
        raise LolgpsError(f"--shapes {text!r}: ROLLOUTSxSTEPS, e.g. 32x5") from None
    DelayConfig(rollouts=rollouts, steps=steps)  # checks them
    return rollouts, steps


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    pybullet_panda = "franka_panda/panda.urdf"
    parser.add_argument("--urdf", nargs="+", default=[str(ROOT / "robots" / "kuka_peg.urdf"),
                                                      pybullet_panda])  # fmt: skip
    parser.add_argument("--shapes", nargs="+", type=shape,
                        default=[(128, 5), (64, 5), (32, 5), (16, 5), (32, 10), (16, 10)])  # fmt: skip
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    return parser.parse_args()


def urdf_path(name: str) -> str:
    """``name``, or pybullet_data's file of that name where no such file exists here."""
    if Path(name).exists():
        return name
    import pybullet_data

    return str(Path(pybullet_data.getDataPath()) / name)


def main() -> None:
    args = parse_args()
    cases = plants(args.seeds)
    print(f"{len(cases)} plants per arm and shape")
    print("arm | rollouts x steps | wrong estimates | smallest margin of a right one")
    for name in args.urdf:
        base, _ = fit_scale(TaskConfig(urdf=urdf_path(name)))
        for rollouts, steps in args.shapes:
            wrong, margin = [], float("inf")
            for plant in cases:
                settings = DelayConfig(rollouts=rollouts, steps=steps, seed=plant.seed)
                estimate = measure_delay(replace(base, plant=plant), settings)
                if abs(estimate.seconds - plant.action_delay) > 1e-9:
                    wrong.append(f"{plant.action_delay * 1000:.0f} ms as "
                                 f"{estimate.seconds * 1000:.0f} ms ({plant})")  # fmt: skip
                else:
                    margin = min(margin, sorted(estimate.relative_rss)[1])
            print(f"{Path(name).stem} | {rollouts} x {steps} | {len(wrong)} | {margin:.3g}")
            for line in wrong:
                print(f"    {line}")


if __name__ == "__main__":
    run(main)
