"""Benchmark of the evaluation's parallelism: the same noiseless rollouts of one policy at N test
positions with one worker (in this process) and with several spawned workers.

    python scripts/bench/bench_eval.py [--urdf robots/kuka_peg.urdf] [--positions 60]
                                       [--workers 2] [--repeats 3] [--checkpoint DIR]

Times are end to end, as ``evaluate_run`` spends them after loading the checkpoints: building
the task (and starting the extra processes, each of which imports torch and builds its
worlds) plus the rollouts and their scoring.
Medians over ``repeats``, the two settings interleaved so drifting load hits both alike; the
speed-up is ``t_1 / t_workers``. On a shared machine compare the ratio, not the seconds.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.evaluation.areas import AreaConfig, sample_area_positions
from lolgps_torch.evaluation.jobs import run_jobs
from lolgps_torch.evaluation.worker import Job, PolicyState
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.state import StateLayout
from lolgps_torch.task import TaskConfig, load_task_arm


def bench_eval(
    task: TaskConfig,
    n_positions: int = 60,
    workers: int = 2,
    repeats: int = 3,
    checkpoint: str | None = None,
    batch_size: int = 10,
) -> dict[str, float]:
    """Median seconds to evaluate ``n_positions`` test positions (area-first, the default areas
    with as many positions per area as needed) with 1 and with ``workers`` workers, and their
    ratio ``speedup = t_1 / t_workers``.

    :param checkpoint: policy folder; default an untrained policy with seed 0.
    """
    areas = AreaConfig()
    per_area = max(areas.positions_per_area, -(-n_positions // areas.n_areas))
    sampled = sample_area_positions(replace(areas, positions_per_area=per_area))
    positions = [(p[0], p[1]) for p in sampled.reshape(-1, 2).tolist()][:n_positions]
    if checkpoint is None:
        layout = StateLayout(load_task_arm(task).dof)
        policy = PolicyState.of("untrained", GaussianPolicy(layout.dX, layout.dU))
    else:
        policy = PolicyState.of(checkpoint, load_policy(checkpoint))
    jobs = [
        Job(0, tuple(positions[i : i + batch_size])) for i in range(0, len(positions), batch_size)
    ]
    times: dict[int, list[float]] = {1: [], workers: []}
    for _ in range(repeats):
        for n in times:
            t0 = time.perf_counter()
            run_jobs(task, [policy], jobs, n, batch_size)
            times[n].append(time.perf_counter() - t0)
    one, many = statistics.median(times[1]), statistics.median(times[workers])
    return {
        "positions": float(len(positions)),
        "one_worker_s": one,
        f"{workers}_workers_s": many,
        "speedup": one / many,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf", help="the arm's URDF")
    parser.add_argument("--positions", type=int, default=60, help="test positions (default 60)")
    parser.add_argument("--workers", type=int, default=2, help="pool size (default 2)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (default 3)")
    parser.add_argument("--checkpoint", default=None, help="policy folder (default: untrained)")
    args = parser.parse_args()
    result = bench_eval(
        TaskConfig(urdf=args.urdf), args.positions, args.workers, args.repeats, args.checkpoint
    )
    for name, value in result.items():
        print(f"{name:>16}: {value:.3f}")


if __name__ == "__main__":
    run(main)
