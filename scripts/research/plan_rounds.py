"""How many C-steps on the arm's model the first controller needs (docs/ALGORITHM.md section 4.2).

    python scripts/research/plan_rounds.py --urdf URDF [URDF ...] [--rounds 2 5 10] [--seed 0]

For each arm and each position of the paper's stream for ``--seed``, the first controller is
planned with each number of ``--rounds`` (``LocalConfig.model_plans``), then rolled out once
without noise and as the first iteration's samples (the same noise for every number of
rounds). Prints per arm and number of rounds: the positions whose noiseless rollout succeeds,
the successful first samples out of all, the worst noiseless final distance, and the plan's
seconds per position (wall time, so compare within one run).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace

from lolgps_torch.cli import run
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner
from lolgps_torch.lolgps.stream import noiseless_distance
from lolgps_torch.task import PegTask, TaskConfig


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", nargs="+", default=["robots/kuka_peg.urdf"])
    parser.add_argument("--rounds", type=int, nargs="+", default=[2, 5, 10])
    parser.add_argument("--seed", type=int, default=0, help="the stream's seed (%(default)s)")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    offsets, _ = default_training_stream(AreaConfig(), args.seed)
    print("| arm | rounds | noiseless successes | first samples successful | worst (m) | plan s |")
    print("|---|---|---|---|---|---|")
    for urdf in args.urdf:
        task = PegTask(TaskConfig(urdf=urdf), n_worlds=LocalConfig().samples)
        threshold = task.config.world.success_threshold
        try:
            for rounds in args.rounds:
                config = replace(LocalConfig(), model_plans=rounds)
                reached = successful = drawn = 0
                worst, seconds = 0.0, 0.0
                for index, offset in enumerate(offsets):
                    learner = LocalLearner(task, offset, config, seed=args.seed * 1000 + index)
                    seconds += learner.plan_time
                    final = noiseless_distance(task, learner.p_cur, offset)
                    reached += final < threshold
                    worst = max(worst, final) if math.isfinite(final) else math.inf
                    samples = learner.sample(learner.p_cur)
                    successful += int(samples.success.sum())
                    drawn += samples.success.numel()
                name = urdf.rsplit("/", 1)[-1]
                print(
                    f"| {name} | {rounds} | {reached}/{len(offsets)} | {successful}/{drawn} | "
                    f"{worst:.4f} | {seconds / len(offsets):.2f} |",
                    flush=True,
                )
        finally:
            task.close()


if __name__ == "__main__":
    run(main)
