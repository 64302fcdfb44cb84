"""Cost of the model prior against the dynamics fit it joins, on one iteration's samples.

    python scripts/bench/bench_model_prior.py [--urdf robots/kuka_peg.urdf] [--repeats 3]

- fit_gmm:        DynamicsFitter.update with the GMM prior (warm-started GMM), the reference;
- linearize_mean: the arm's control step linearised at the T-1 per-step sample means (what
                  the model prior evaluates);
- linearize_all:  the same at all N x (T-1) samples;
- fit_model:      DynamicsFitter.update with prior="model" (GMM, linearisation, mixing);
- plan:           the first controller planned on the model (``LocalConfig.model_plans``
                  C-steps, :func:`lolgps_torch.lolgps.local.planned_controller`), once per
                  condition;
- sample:         one iteration's 5 rollouts in the simulator (one process).
Medians over the repeats, as ratios to fit_gmm measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import replace

from lolgps_torch.cli import run
from lolgps_torch.dynamics import DynamicsConfig, DynamicsFitter
from lolgps_torch.lolgps.local import (
    LocalConfig,
    LocalLearner,
    initial_controller,
    planned_controller,
)
from lolgps_torch.task import PegTask, TaskConfig


def median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    task = PegTask(TaskConfig(urdf=args.urdf), n_worlds=5)
    try:
        config = LocalConfig()
        learner = LocalLearner(task, (0.0, 0.0), config, seed=0)
        hold = initial_controller(task, config)
        samples = learner.sample(learner.p_cur)
        x, u = samples.x, samples.u  # [5, T, dX], [5, T, dU]
        gmm = DynamicsFitter(DynamicsConfig())
        model = DynamicsFitter(replace(DynamicsConfig(), prior="model"), task.model.linearize)
        for fitter in (gmm, model):
            fitter.update(x, u)  # cold start of the GMM, not timed
        states, actions = x[:, :-1], u[:, :-1]
        rows = {
            "fit_gmm": median_time(lambda: gmm.update(x, u), args.repeats),
            "linearize_mean": median_time(
                lambda: task.model.linearize(states.mean(0), actions.mean(0)), args.repeats
            ),
            "linearize_all": median_time(
                lambda: task.model.linearize(
                    states.reshape(-1, x.shape[-1]), actions.reshape(-1, u.shape[-1])
                ),
                args.repeats,
            ),
            "fit_model": median_time(lambda: model.update(x, u), args.repeats),
            "plan": median_time(
                lambda: planned_controller(task, learner.targets, hold, config),
                args.repeats,
            ),
            "sample": median_time(lambda: learner.sample(learner.p_cur), args.repeats),
        }
    finally:
        task.close()
    print(f"states per iteration: {x.shape[0]} x {x.shape[1] - 1}")
    for name, seconds in rows.items():
        print(f"  {name:<16}{seconds:10.3f} s {seconds / rows['fit_gmm']:8.2f} x fit_gmm")


if __name__ == "__main__":
    run(main)
