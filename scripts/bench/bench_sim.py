"""Benchmark of the simulators: the seconds one rollout takes in MuJoCo as a ratio to PyBullet,
the reference, both measured in this run.

    python scripts/bench/bench_sim.py [--urdf robots/kuka_peg.urdf] [--samples 5] [--repeats 5]

Per simulator, one process's task at the nominal hole samples batches of ``samples`` rollouts
of the first local controller (the hold of the start pose planned on the arm's model, which
inserts the peg, with its smoothed exploration noise, seed 0) as the local learner's first
iteration does: stepping with contact, gravity compensation, state extraction and the cost.
Then the policy's check as the S-step runs it: one noiseless rollout of a global policy (an
untrained one of the default architecture: acting costs the same) at each of the paper
stream's 8 training positions.  The two simulators' batches alternate, so drifting load hits
both alike; medians over ``repeats``, and the ratio ``mujoco / pybullet`` per rollout, of wall
time and of this process's CPU time (``time.process_time``, which other processes on a shared
machine disturb less).  On a shared machine compare the ratios, not the seconds.

    python scripts/bench/bench_sim.py --streams SEED ... --out DIR [--urdf URDF] [-- FLAGS]

runs instead the default stream (``run_stream.py --urdf URDF --seed SEED``, with FLAGS) on
each simulator, one run at a time, the two simulators' order alternating from seed to seed,
into ``DIR/<sim>-seed<SEED>``, and prints per run its wall time, its CPU time (its processes'
and their workers'), the positions its final policy reaches, its rollouts (local and the
policy's) and any failure, and per seed the MuJoCo / PyBullet ratio of wall and CPU time.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import get_args

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, planned_controller
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.sim.simulator import Simulator
from lolgps_torch.task import PegTask, TaskConfig


def bench_sim(urdf: str, samples: int = 5, repeats: int = 5) -> dict[str, float]:
    """Median seconds per rollout in each simulator (``<sim>_s``), its CPU seconds
    (``<sim>_cpu_s``), its success rate over the timed batches (``<sim>_success``), and
    ``ratio = mujoco_s / pybullet_s``, ``cpu_ratio`` the same of CPU seconds; the same of the
    policy's rollouts with the prefix ``policy_``."""
    names = get_args(Simulator)
    tasks = {name: PegTask(TaskConfig(urdf=urdf, sim=name), n_worlds=1) for name in names}
    result = _local_rollouts(tasks, samples, repeats)
    try:
        result |= {f"policy_{k}": v for k, v in _policy_rollouts(tasks, repeats).items()}
    finally:
        for task in tasks.values():
            task.close()
    return result


def _ratios(times: dict[str, list[float]], cpu: dict[str, list[float]]) -> dict[str, float]:
    """Medians per simulator and the MuJoCo / PyBullet ratios of wall and CPU time."""
    result = {f"{name}_s": statistics.median(times[name]) for name in times}
    result |= {f"{name}_cpu_s": statistics.median(cpu[name]) for name in cpu}
    result["ratio"] = result["mujoco_s"] / result["pybullet_s"]
    result["cpu_ratio"] = result["mujoco_cpu_s"] / result["pybullet_cpu_s"]
    return result


def _policy_rollouts(tasks: dict[str, PegTask], repeats: int) -> dict[str, float]:
    """Seconds per noiseless rollout of an untrained policy at the paper stream's positions."""
    positions, _ = default_training_stream(AreaConfig(), seed=0)
    times: dict[str, list[float]] = {name: [] for name in tasks}
    cpu: dict[str, list[float]] = {name: [] for name in tasks}
    for _ in range(repeats):
        for name, task in tasks.items():
            actor = policy_actor(GaussianPolicy(task.layout.dX, task.arm.dof), task.model)
            t0, c0 = time.perf_counter(), time.process_time()
            task.sample(actor, positions)
            times[name].append((time.perf_counter() - t0) / len(positions))
            cpu[name].append((time.process_time() - c0) / len(positions))
    return _ratios(times, cpu)


def _local_rollouts(tasks: dict[str, PegTask], samples: int, repeats: int) -> dict[str, float]:
    """Seconds per rollout of the first local controller, and its success rate."""
    names = list(tasks)
    config = LocalConfig(samples=samples)
    learners = {
        name: LocalLearner(task, (0.0, 0.0), config, seed=0) for name, task in tasks.items()
    }
    first = {
        name: planned_controller(tasks[name], learner.targets, learner.p_cur, config)[0]
        for name, learner in learners.items()
    }
    times: dict[str, list[float]] = {name: [] for name in names}
    cpu: dict[str, list[float]] = {name: [] for name in names}
    successes: dict[str, list[float]] = {name: [] for name in names}
    for _ in range(repeats):
        for name, learner in learners.items():
            t0, c0 = time.perf_counter(), time.process_time()
            batch = learner.sample(first[name])
            times[name].append((time.perf_counter() - t0) / samples)
            cpu[name].append((time.process_time() - c0) / samples)
            successes[name].append(float(batch.success.double().mean()))
    result = _ratios(times, cpu)
    return result | {f"{name}_success": statistics.mean(successes[name]) for name in names}


def bench_streams(urdf: str, seeds: list[int], out: Path, flags: list[str]) -> None:
    """Run and print the default stream on each simulator per seed (module docstring)."""
    script = Path(__file__).resolve().parents[1] / "run_stream.py"
    names = list(get_args(Simulator))
    for i, seed in enumerate(seeds):
        measured: dict[str, tuple[float, float]] = {}
        for name in names if i % 2 == 0 else names[::-1]:
            folder = out / f"{name}-seed{seed}"
            command = [sys.executable, str(script), "--urdf", urdf, "--sim", name, "--seed",
                       str(seed), "--out", str(folder), *flags]  # fmt: skip
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            with open(out / f"{name}-seed{seed}.log", "w") as log:
                code = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode
            wall = time.perf_counter() - t0
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
            measured[name] = (wall, cpu)
            if code != 0:
                print(f"seed {seed} {name}: exit status {code}, see {folder}.log")
                continue
            entries = json.loads((folder / "summary.json").read_text())["conditions"]
            reached = sum(bool(e["policy_success_end"]) for e in entries)
            failures = [e["condition"] for e in entries if e["failure"]]
            print(f"seed {seed} {name:>8}: {wall:7.1f} s wall, {cpu:7.1f} s CPU, "
                  f"{reached}/{len(entries)} reached, {sum(e['rollouts'] for e in entries)} "
                  f"rollouts, {sum(e['policy_rollouts'] for e in entries)} policy rollouts, "
                  f"failures at {failures}", flush=True)  # fmt: skip
        if len(measured) == 2:
            (pw, pc), (mw, mc) = measured["pybullet"], measured["mujoco"]
            print(f"seed {seed} mujoco / pybullet: wall {mw / pw:.2f}, CPU {mc / pc:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf", help="the arm's URDF")
    parser.add_argument("--samples", type=int, default=5, help="rollouts a batch (default 5)")
    parser.add_argument("--repeats", type=int, default=5, help="timed batches (default 5)")
    parser.add_argument("--streams", type=int, nargs="+", metavar="SEED",
                        help="run the default stream on each simulator at these seeds")  # fmt: skip
    parser.add_argument("--out", help="the streams' folder (with --streams)")
    args, flags = parser.parse_known_args()
    if args.samples < 1 or args.repeats < 1:
        raise LolgpsError("--samples and --repeats must be at least 1")
    if args.streams:
        if args.out is None:
            raise LolgpsError("--streams needs --out")
        Path(args.out).mkdir(parents=True, exist_ok=True)
        bench_streams(args.urdf, args.streams, Path(args.out), [f for f in flags if f != "--"])
        return
    if flags:
        raise LolgpsError(f"unrecognised arguments: {' '.join(flags)}")
    for name, value in bench_sim(args.urdf, args.samples, args.repeats).items():
        print(f"{name:>16}: {value:.4f}")


if __name__ == "__main__":
    run(main)
