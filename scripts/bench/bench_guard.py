"""Benchmark of the guard's prediction: the seconds a policy rollout takes through the whole
guard (its brake and the prediction that keeps the arm within its limits) as a ratio to the
same rollout with the guard off, both measured in this run.

    python scripts/bench/bench_guard.py --run RUN [--repeats 5]

The policy is the run's final one; it rolls out without noise at each of the run's training
positions, once with its guard and once without (``PolicyConfig.guard`` false), the two
alternating so that drifting load hits both alike. It prints the median seconds per rollout of
each, and the ratio ``guarded / unguarded`` of wall time and of this process's CPU time
(``time.process_time``, which other processes on a shared machine disturb less).
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

from lolgps_torch.cli import run
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import GaussianPolicy, policy_actor


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True, help="a run folder")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    loaded = load_run(args.run)
    guarded = loaded.policy()
    unguarded = GaussianPolicy(
        guarded.dX, guarded.dU, replace(guarded.config, guard=False), guarded.x_mean.device
    )
    unguarded.set_guard(guarded.guard)  # the trip speeds' steps first, so the shapes agree
    unguarded.load_state_dict(guarded.state_dict())
    task = loaded.make_task(n_worlds=1)
    offsets = loaded.info.conditions
    wall: dict[str, list[float]] = {"guarded": [], "unguarded": []}
    cpu: dict[str, list[float]] = {"guarded": [], "unguarded": []}
    try:
        for _ in range(args.repeats):
            for name, policy in (("guarded", guarded), ("unguarded", unguarded)):
                started, process = time.perf_counter(), time.process_time()
                for offset in offsets:
                    task.sampler.rollout(policy_actor(policy, task.model), [offset])
                wall[name].append((time.perf_counter() - started) / len(offsets))
                cpu[name].append((time.process_time() - process) / len(offsets))
    finally:
        task.close()
    for name in wall:
        print(f"{name:>10}: {statistics.median(wall[name]):.3f} s wall, "
              f"{statistics.median(cpu[name]):.3f} s CPU per rollout")  # fmt: skip
    print(
        "guarded / unguarded: wall "
        f"{statistics.median(wall['guarded']) / statistics.median(wall['unguarded']):.2f}, CPU "
        f"{statistics.median(cpu['guarded']) / statistics.median(cpu['unguarded']):.2f}"
    )


if __name__ == "__main__":
    run(main)
