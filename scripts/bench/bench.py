"""Benchmarks, each reported as a ratio to a reference measured in the same run.

    python scripts/bench/bench.py [--urdf robots/kuka_peg.urdf] [--repeats 5] [--only NAME ...]
        [--reference REV]
    python scripts/bench/bench.py --runs RUN [RUN ...]

- default:   the default stream (``run_stream.py --urdf URDF``, seed 0) run twice, with one
             rollout worker and with the default (this machine's cores): its wall time, and
             the sums of its parts from metrics.jsonl (sampling, dynamics fits, C-steps with
             the plans on the model, S-steps with their closed-loop checks) of each run as
             ratios to the one-worker run's sampling (with workers, the plans are made during
             the S-steps); with ``--reference REV``, the same stream at git
             revision REV (checked out into a temporary worktree) first, in the same run, its
             parts as ratios to its own sampling, and each wall time as a ratio to it.
- physics:   raw PyBullet stepping rate of this world (substeps/s: the same worlds, the arm
             held at q0 by constant gravity torques sent every substep, nothing else) against
             the rollout pipeline (initial controller, smoothed noise, gravity compensation,
             state extraction, cost) from the same pose, as a ratio.
- algorithm: one dynamics fit (GMM + per-step regression) and one C-step with its dual
             search at the task's sizes, as ratios to the sampling time of the same iteration.
- stream:    the share of a short stream's wall time (2 conditions, sampling, fits, C-steps,
             S-steps, evaluation rollouts) spent inside PyBullet's stepSimulation.
- sweep:     4 cells (seeds 0-3) of a 2-condition stream run by scripts/sweep.py on a local Ray
             instance of 2 CPUs, against the same 4 run_stream.py commands one after another
             (the speed-up; one run of each, not the median: they take minutes).
- model_prior: on one iteration's samples at the nominal hole, as ratios to the dynamics fit
             with the GMM prior (warm-started): the arm's control step linearised at the T-1
             per-step sample means (what the model prior evaluates) and at all N x (T-1)
             samples, the fit with the model prior (GMM, linearisation, mixing), the first
             controller planned on the model (``LocalConfig.model_plans`` C-steps), and the
             iteration's rollouts in one process.
Medians over the repeats; the machine is noisy, so compare ratios, not seconds.

``--runs`` measures nothing: it prints one markdown row per finished run folder, the final
policy's successes at the training positions (summary.json), the run's wall seconds
(metrics.jsonl's last line), the seconds metrics.jsonl records for sampling, dynamics fits, C-steps (with
the plans on the model), the S-steps' fits (with their repair rounds) and the S-steps' policy
rollouts (the checks and visits), the rest of the wall time (start-up: imports of the script
aside, the placement, the probes before the stream, the worker processes), the rollouts on
the arm by kind (summary.json's ``arm_rollouts``; "-" for runs made before they were
counted), and the repair rounds.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import torch

import lolgps_torch.sim.world as world_module
from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.dynamics import DynamicsConfig, DynamicsFitter
from lolgps_torch.lolgps import StreamConfig, make_learner
from lolgps_torch.lolgps.local import (
    LocalConfig,
    LocalLearner,
    initial_controller,
    iterate,
    planned_controller,
)
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld
from lolgps_torch.task import PegTask, TaskConfig


def median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_physics(task: PegTask, repeats: int) -> dict[str, float]:
    """Substeps per second: bare stepping vs the full rollout pipeline, same worlds."""
    worlds = cast(list[PegWorld], task.sampler.worlds)  # the default simulator's
    T, substeps = task.T, task.config.world.substeps
    q0 = task.q0.numpy()
    w0 = worlds[0]
    zeros = [0.0] * len(w0.movable)
    w0.reset(q0)
    gravity = pb.calculateInverseDynamics(
        w0.body, w0._q_all, zeros, zeros, physicsClientId=w0.client
    )
    tau = [
        gravity[i] for i in w0.actuated_in_movable
    ]  # holds q0, as the pipeline's controller does

    def raw() -> None:
        for w in worlds:
            w.reset(q0)
            for _ in range(T * substeps):
                pb.setJointMotorControlArray(
                    w.body, w.joint_ids, pb.TORQUE_CONTROL, forces=tau, physicsClientId=w.client
                )
                pb.stepSimulation(physicsClientId=w.client)

    learner = LocalLearner(task, (0.0, 0.0), LocalConfig(samples=len(worlds)), seed=0)

    def pipeline() -> None:
        learner.sample(learner.p_cur)

    n = len(worlds) * T * substeps
    raw_rate = n / median_time(raw, repeats)
    pipe_rate = n / median_time(pipeline, repeats)
    return {
        "raw_substeps_per_s": raw_rate,
        "pipeline_substeps_per_s": pipe_rate,
        "pipeline_over_raw": pipe_rate / raw_rate,
    }


def bench_algorithm(task: PegTask, repeats: int) -> dict[str, float]:
    """Fit and C-step times against the sampling time of the same iteration (median)."""
    learner = LocalLearner(task, (0.0, 0.0), LocalConfig(samples=len(task.sampler.worlds)), seed=0)
    rows = []
    for i in range(max(repeats, 5)):
        _, _, it = iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
        rows.append((it.time_sample, it.time_fit, it.time_cstep))
    rows = rows[1:]  # the first iteration has no warm-started GMM
    sample = statistics.median(r[0] for r in rows)
    fit = statistics.median(r[1] for r in rows)
    cstep = statistics.median(r[2] for r in rows)
    return {
        "sample_s": sample,
        "fit_s": fit,
        "cstep_s": cstep,
        "fit_over_sample": fit / sample,
        "cstep_over_sample": cstep / sample,
        "algorithm_over_sample": (fit + cstep) / sample,
    }


class _TimedPyBullet:
    """PyBullet with the time spent inside stepSimulation added up."""

    def __init__(self) -> None:
        self.seconds = 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(pb, name)

    def stepSimulation(self, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        out = pb.stepSimulation(*args, **kwargs)
        self.seconds += time.perf_counter() - t0
        return out


def bench_stream(task: PegTask, repeats: int) -> dict[str, float]:
    """Share of a short stream's wall time spent inside physics stepping (2 conditions,
    the default settings but 3 success phases)."""
    timed = _TimedPyBullet()
    world_module.pb = timed  # type: ignore[assignment]
    try:
        with tempfile.TemporaryDirectory() as out:
            config = StreamConfig(success_phases=3, max_iterations=10)
            learner = make_learner("lolgps", task, config, RunFolder(out), lambda record: None)
            t0 = time.perf_counter()
            learner.run([(0.0, 0.0), (0.01, -0.01)], lambda entry: None)
            wall = time.perf_counter() - t0
    finally:
        world_module.pb = pb
    return {
        "stream_wall_s": wall,
        "physics_s": timed.seconds,
        "physics_share": timed.seconds / wall,
    }


SWEEP_CONDITIONS = "[[0.02, 0.02], [-0.02, 0.02]]"


def bench_sweep(task: PegTask, repeats: int) -> dict[str, float]:
    """Wall time of 4 short streams one after another against the same 4 as a sweep's cells
    on a local Ray instance of 2 CPUs (Ray's start-up included)."""
    scripts = Path(__file__).resolve().parents[1]
    urdf = task.config.urdf
    with tempfile.TemporaryDirectory() as tmp:
        conditions = Path(tmp) / "conditions.json"
        conditions.write_text(SWEEP_CONDITIONS)
        t0 = time.perf_counter()
        for seed in range(4):
            command = [sys.executable, str(scripts / "run_stream.py"), "--urdf", urdf,
                       "--conditions", str(conditions), "--seed", str(seed),
                       "--out", f"{tmp}/seq-{seed}"]  # fmt: skip
            subprocess.run(command, check=True, capture_output=True)
        sequential = time.perf_counter() - t0
        t0 = time.perf_counter()
        command = [sys.executable, str(scripts / "sweep.py"), "--seeds", "0-3", "--urdf", urdf,
                   "--conditions", str(conditions), "--num-cpus", "2", "--out", f"{tmp}/sweep"]  # fmt: skip
        subprocess.run(command, check=True, capture_output=True)
        swept = time.perf_counter() - t0
    return {"sequential_s": sequential, "sweep_s": swept, "speedup": sequential / swept}


PARTS = {"sampling": "time_sample", "fit": "time_fit", "C-step": "time_cstep",
         "S-step": "time_distill"}  # fmt: skip


def _default_stream(root: Path, urdf: str, out: Path, flags: list[str]) -> dict[str, float]:
    """Run the default stream of the checkout at ``root`` into ``out``: wall time, and its
    parts summed from metrics.jsonl (seconds)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    command = [sys.executable, str(root / "scripts" / "run_stream.py"), "--urdf", urdf,
               "--out", str(out), *flags]  # fmt: skip
    t0 = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, env=env, cwd=root)
    wall = time.perf_counter() - t0
    records = RunFolder(out).read_metrics()
    parts = {name: sum(r.get(key, 0.0) for r in records) for name, key in PARTS.items()}
    return {"wall": wall, **parts}


def bench_default(task: PegTask, repeats: int, reference: str | None = None) -> dict[str, float]:
    """The default stream's parts as ratios to its sampling with one worker, and its wall time
    with one worker and with the default number (and at ``reference``, if given)."""
    root = Path(__file__).resolve().parents[2]
    urdf = str(Path(task.config.urdf).resolve())
    results: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        base = None
        if reference is not None:
            tree = Path(tmp) / "reference"
            subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(tree),
                            reference], check=True, capture_output=True)  # fmt: skip
            try:
                base = _default_stream(tree, urdf, Path(tmp) / "ref", [])
            finally:
                subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force",
                                str(tree)], check=True, capture_output=True)  # fmt: skip
            results["reference_wall_s"] = base["wall"]
            for name in PARTS:
                results[f"reference {name} / sampling"] = base[name] / base["sampling"]
        one = _default_stream(root, urdf, Path(tmp) / "one", ["--workers", "1"])
        default = _default_stream(root, urdf, Path(tmp) / "default", [])
    results["wall_s (1 worker)"] = one["wall"]
    results[f"wall_s ({os.cpu_count()} workers)"] = default["wall"]
    for name in PARTS:
        results[f"{name} / sampling"] = one[name] / one["sampling"]
    for name in PARTS:  # the same stream: the parts differ by the work the workers take on
        results[f"{name} ({os.cpu_count()} workers) / sampling"] = default[name] / one["sampling"]
    algorithm = one["fit"] + one["C-step"] + one["S-step"]
    results["fit + C-step + S-step / sampling"] = algorithm / one["sampling"]
    results["sampling (default workers) / (1 worker)"] = default["sampling"] / one["sampling"]
    if base is not None:
        results["wall (default workers) / reference"] = default["wall"] / base["wall"]
    return results


def bench_model_prior(task: PegTask, repeats: int) -> dict[str, float]:
    """The model prior's parts against the GMM-prior fit, on one iteration's samples."""
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
    seconds = {
        "fit_gmm": median_time(lambda: gmm.update(x, u), repeats),
        "linearize_mean": median_time(
            lambda: task.model.linearize(states.mean(0), actions.mean(0)), repeats
        ),
        "linearize_all": median_time(
            lambda: task.model.linearize(
                states.reshape(-1, x.shape[-1]), actions.reshape(-1, u.shape[-1])
            ),
            repeats,
        ),
        "fit_model": median_time(lambda: model.update(x, u), repeats),
        "plan": median_time(
            lambda: planned_controller(task, learner.targets, hold, config), repeats
        ),
        "sample": median_time(lambda: learner.sample(learner.p_cur), repeats),
    }
    results = {"fit_gmm_s": seconds["fit_gmm"]}
    for name, value in seconds.items():
        if name != "fit_gmm":
            results[f"{name} / fit_gmm"] = value / seconds["fit_gmm"]
    return results


def stream_times(paths: list[str]) -> None:
    """Print the ``--runs`` table (module docstring)."""
    kinds = ("start", "sample", "probe", "visit", "total")
    print(
        "| run | final | wall s | sampling s | fits s | C-steps s | S-step fits s | visits s | "
        "start-up and the rest s | arm rollouts: " + " / ".join(kinds) + " | repair rounds |"
    )
    print("|---" * 11 + "|")
    for path in paths:
        folder = RunFolder(path)
        sums = dict.fromkeys((*PARTS.values(), "time_visits"), 0.0)
        repairs, wall = 0, float("nan")
        for record in folder.read_metrics():
            if record.get("event") == "finished":
                wall = float(record["seconds"])
            for phase in sums:
                sums[phase] += float(record.get(phase) or 0.0)
            repairs += int(record.get("repairs") or 0)
        summary = folder.read_summary()
        entries = summary["conditions"]
        final = sum(bool(e["policy_success_end"]) for e in entries)
        fits = sums["time_distill"] - sums["time_visits"]
        parts = [sums["time_sample"], sums["time_fit"], sums["time_cstep"], fits]
        rest = wall - sum(parts) - sums["time_visits"]
        counted = summary.get("arm_rollouts", {})
        rollouts = " / ".join(str(counted[k]) if k in counted else "-" for k in kinds)
        times = " | ".join(f"{v:.1f}" for v in (wall, *parts, sums["time_visits"], rest))
        print(f"| {folder.path.name} | {final}/{len(entries)} | {times} | {rollouts} | {repairs} |")


BENCHES = {
    "default": bench_default,
    "physics": bench_physics,
    "algorithm": bench_algorithm,
    "stream": bench_stream,
    "sweep": bench_sweep,
    "model_prior": bench_model_prior,
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--only", nargs="*", choices=sorted(BENCHES), default=None)
    parser.add_argument(
        "--reference",
        default=None,
        help="git revision whose default stream the default bench also times, in the same run",
    )
    parser.add_argument("--runs", nargs="+", default=None, help="finished run folders: their times")
    args = parser.parse_args()
    if args.runs:
        stream_times(args.runs)
        return
    BENCHES["default"] = functools.partial(bench_default, reference=args.reference)
    task = PegTask(TaskConfig(urdf=args.urdf), n_worlds=5)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    for name in args.only or BENCHES:
        results = BENCHES[name](task, args.repeats)
        print(f"[{name}]")
        for key, value in results.items():
            print(f"  {key:<28}{value:12.4g}")
    task.close()


if __name__ == "__main__":
    run(main)
