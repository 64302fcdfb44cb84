"""The dynamics fit against the sampling it fits, and its held-out accuracy.

    python scripts/bench/bench_fit.py [--urdf robots/kuka_peg.urdf] [--iterations 10]
                                      [--tolerances 0.05 0.2 1.0] [--samples FILE ...]

Runs the trajectory-centric loop at the nominal hole for ``--iterations`` iterations and keeps
each iteration's samples; or, with ``--samples``, takes the samples and their sampling CPU
time from files written by ``scripts/research/local_trace.py --save-samples`` (a stream's
conditions, re-learnt as in the stream), each replayed on its own and the rows summed. Then replays the sequence of fits (one :class:`DynamicsFitter` fed
the iterations in order, as the learner does) once per EM tolerance, and reports:

- the fit's CPU time as a ratio to the sampling CPU time of the same iterations, split into
  the GMM update (EM), the prior's evaluation and the per-step regression;
- the EM iterations per update;
- the held-out one-step prediction error: the fit of iteration i predicts the states of
  iteration i+1's rollouts, ``mean_{n,t} |x_{t+1} - (F_t [x_t; u_t] + f_t)|^2``, as a ratio
  to that of the default tolerance (same samples for every row).

CPU times (``time.process_time``) on one torch thread, so a loaded machine changes them less.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch
from torch import Tensor

from lolgps_torch.cli import run
from lolgps_torch.dynamics import DynamicsConfig, DynamicsFitter
from lolgps_torch.dynamics.fit import gaussian_regression
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import Trajectories


def one_step_error(F: Tensor, f: Tensor, samples: Trajectories) -> float:
    """``mean_{n,t} |x_{t+1} - (F_t [x_t; u_t] + f_t)|^2`` over ``samples`` (t < T-1)."""
    xu = torch.cat([samples.x[:, :-1], samples.u[:, :-1]], dim=-1)  # [N, T-1, dX+dU]
    predicted = torch.einsum("tij,ntj->nti", F, xu) + f
    return float((samples.x[:, 1:] - predicted).square().sum(-1).mean())


def replay_fits(config: DynamicsConfig, history: list[Trajectories]) -> dict[str, float]:
    """Fit the iterations in order with one fitter; times (s, summed), EM iterations per
    update and the mean held-out one-step error."""
    fitter = DynamicsFitter(config)
    assert fitter.prior is not None
    times = {"em_s": 0.0, "evaluate_s": 0.0, "regression_s": 0.0}
    em, errors = [], []
    for i, samples in enumerate(history):
        X = torch.cat([samples.x[:, :-1], samples.u[:, :-1]], dim=-1)
        Y = samples.x[:, 1:]
        t0 = time.process_time()
        em.append(len(fitter.prior.update(X, Y)))
        t1 = time.process_time()
        prior = fitter.prior.evaluate(X, Y)
        t2 = time.process_time()
        F, f, _ = gaussian_regression(X, Y, prior, config.regression_reg)
        t3 = time.process_time()
        times["em_s"] += t1 - t0
        times["evaluate_s"] += t2 - t1
        times["regression_s"] += t3 - t2
        if i + 1 < len(history):
            errors.append(one_step_error(F, f, history[i + 1]))
    return {**times, "em_iterations": statistics.fmean(em), "error": statistics.fmean(errors)}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--tolerances", type=float, nargs="+", default=[0.05, 0.2, 1.0])
    parser.add_argument("--samples", nargs="+", default=None, help="local_trace.py sample files")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.samples is not None:
        histories, sample_s = [], 0.0
        for path in args.samples:
            stored = torch.load(path, weights_only=False)
            histories.append([Trajectories(*h) for h in stored["samples"]])
            sample_s += stored["sample_s"]
        where = f"{sum(map(len, histories))} iterations of {len(histories)} conditions"
        report(histories, sample_s, args.tolerances, where)
        return
    task = PegTask(TaskConfig(urdf=args.urdf), n_worlds=5)
    learner = LocalLearner(task, (0.0, 0.0), LocalConfig(), seed=0)
    history = []
    for iteration in range(args.iterations):
        samples, _, _ = iterate(learner, learner.p_cur, None, False, (0, iteration, 0.0))
        history.append(samples)
    t0 = time.process_time()  # sampling of the last controller, as the iterations' reference
    for _ in range(3):
        learner.sample(learner.p_cur)
    sample_s = (time.process_time() - t0) / 3 * len(history)
    task.close()
    report([history], sample_s, args.tolerances, f"{len(history)} iterations at the nominal hole")


def report(histories: list[list[Trajectories]], sample_s: float, tolerances: list[float],
           where: str) -> None:  # fmt: skip
    """Print one row per EM tolerance: the fits replayed over every history, summed."""
    default = DynamicsConfig()

    def replay(config: DynamicsConfig) -> dict[str, float]:
        rows = [replay_fits(config, history) for history in histories]
        total = {k: sum(r[k] for r in rows) for k in ("em_s", "evaluate_s", "regression_s")}
        return {
            **total,
            "em_iterations": statistics.fmean(r["em_iterations"] for r in rows),
            "error": statistics.fmean(r["error"] for r in rows),
        }

    reference = replay(default)
    print(f"{where}; sampling {sample_s:.2f} s CPU")
    header = "em_tolerance  fit/sample  em/sample  eval/sample  regr/sample  EM its  error/default"
    print(header)
    for tolerance in tolerances:
        row = replay(replace(default, em_tolerance=tolerance))
        total = row["em_s"] + row["evaluate_s"] + row["regression_s"]
        print(
            f"{tolerance:12.3g}  {total / sample_s:10.3f}  {row['em_s'] / sample_s:9.3f}  "
            f"{row['evaluate_s'] / sample_s:11.3f}  {row['regression_s'] / sample_s:11.3f}  "
            f"{row['em_iterations']:6.1f}  {row['error'] / reference['error']:13.4f}"
        )


if __name__ == "__main__":
    run(main)
