"""The dynamics fit and p_pre's fit against the sampling they fit, and the held-out accuracy.

    python scripts/bench/bench_fit.py [--urdf robots/kuka_peg.urdf] [--iterations 10]
                                      [--tolerances 0.05 0.2 1.0] [--samples FILE ...]
                                      [--reference REV] [--repeats 3]

Runs the trajectory-centric loop at the nominal hole for ``--iterations`` iterations and keeps
each iteration's samples; or, with ``--samples``, takes the samples and their sampling CPU
time from files written by ``scripts/research/local_trace.py --save-samples`` (a stream's
conditions, re-learnt as in the stream), each replayed on its own and the rows summed. Then
replays the sequence of fits (one :class:`DynamicsFitter` fed the iterations in order, as the
learner does) once per EM tolerance; for a condition after the first, also p_pre's fits (the
global policy of the run's checkpoint linearised around the states the trace linearised it
around, with its own GMM prior, as the stream does). It reports:

- the fits' CPU time as a ratio to the sampling CPU time of the same iterations, split into
  the GMM update (EM), the prior's evaluation, the per-step regression and p_pre's fit;
- the EM iterations per update of the dynamics' GMM;
- the held-out one-step prediction error: the fit of iteration i predicts the states of
  iteration i+1's rollouts, ``mean_{n,t} |x_{t+1} - (F_t [x_t; u_t] + f_t)|^2``, as a ratio
  to that of the default tolerance (same samples for every row).

With ``--reference REV`` the same replay also runs on the package at git revision REV (checked
out into a temporary worktree), alternating with this one ``--repeats`` times (each time the
smallest of the repeats); the errors are then ratios to REV's default tolerance and a last
line gives this revision's fit time over REV's. CPU times (``time.process_time``) on one torch
thread, so a loaded machine changes them less.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from lolgps_torch.cli import run
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.dynamics import DynamicsConfig, DynamicsFitter, prior_from_config
from lolgps_torch.dynamics.fit import gaussian_regression
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
from lolgps_torch.policy import GaussianPolicy, linearize_policy
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import Trajectories

PARTS = ("em_s", "evaluate_s", "regression_s", "pre_s")
Linearisations = tuple[GaussianPolicy, list[Tensor]]  # the policy, the states of each iteration


def one_step_error(F: Tensor, f: Tensor, samples: Trajectories) -> float:
    """``mean_{n,t} |x_{t+1} - (F_t [x_t; u_t] + f_t)|^2`` over ``samples`` (t < T-1)."""
    xu = torch.cat([samples.x[:, :-1], samples.u[:, :-1]], dim=-1)  # [N, T-1, dX+dU]
    predicted = torch.einsum("tij,ntj->nti", F, xu) + f
    return float((samples.x[:, 1:] - predicted).square().sum(-1).mean())


def replay_fits(
    config: DynamicsConfig, history: list[Trajectories], pre: Linearisations | None
) -> dict[str, float]:
    """Fit the iterations in order with one fitter (and linearise ``pre``'s policy at each
    iteration's states with one prior); times (s, summed), EM iterations per update and the
    mean held-out one-step error."""
    fitter = DynamicsFitter(config)
    pre_prior = prior_from_config(config)
    assert fitter.prior is not None
    times = dict.fromkeys(PARTS, 0.0)
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
        if pre is not None:
            linearize_policy(pre[0], pre[1][i], pre_prior, config.regression_reg)
        times["pre_s"] += time.process_time() - t3
        times["em_s"] += t1 - t0
        times["evaluate_s"] += t2 - t1
        times["regression_s"] += t3 - t2
        if i + 1 < len(history):
            errors.append(one_step_error(F, f, history[i + 1]))
    return {**times, "em_iterations": statistics.fmean(em), "error": statistics.fmean(errors)}


def replay(
    config: DynamicsConfig, histories: list[list[Trajectories]], pres: list[Linearisations | None]
) -> dict[str, float]:
    """The fits replayed over every history: times summed, EM iterations and errors averaged."""
    rows = [replay_fits(config, h, pre) for h, pre in zip(histories, pres, strict=True)]
    return {
        **{k: sum(r[k] for r in rows) for k in PARTS},
        "em_iterations": statistics.fmean(r["em_iterations"] for r in rows),
        "error": statistics.fmean(r["error"] for r in rows),
    }


def load_samples(paths: list[str]) -> tuple[list[list[Trajectories]], list[Linearisations | None],
                                            float]:  # fmt: skip
    """The histories, p_pre's policies and states (None for a first condition or a file without
    them) and the summed sampling CPU seconds of ``local_trace.py --save-samples`` files."""
    histories: list[list[Trajectories]] = []
    pres: list[Linearisations | None] = []
    sample_s = 0.0
    for path in paths:
        stored = torch.load(path, weights_only=True)
        histories.append([Trajectories(*h) for h in stored["samples"]])
        sample_s += stored["sample_s"]
        pre = None
        if stored.get("accepted_x") and stored["condition"] > 0:
            checkpoint = RunFolder(stored["run"]).checkpoint_dir(stored["condition"] - 1)
            pre = (load_policy(checkpoint), stored["accepted_x"])
        pres.append(pre)
    return histories, pres, sample_s


def nominal_samples(urdf: str, iterations: int) -> tuple[list[Trajectories], float]:
    """``iterations`` iterations of the loop at the nominal hole, and as their sampling CPU
    seconds the last controller's sampling repeated."""
    task = PegTask(TaskConfig(urdf=urdf), n_worlds=5)
    learner = LocalLearner(task, (0.0, 0.0), LocalConfig(), seed=0)
    history = []
    for iteration in range(iterations):
        samples, _, _ = iterate(learner, learner.p_cur, None, False, (0, iteration, 0.0))
        history.append(samples)
    t0 = time.process_time()
    for _ in range(3):
        learner.sample(learner.p_cur)
    sample_s = (time.process_time() - t0) / 3 * len(history)
    task.close()
    return history, sample_s


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """One replay per tolerance (the default's first) of this package on the arguments' samples."""
    torch.set_num_threads(1)
    if args.samples is not None:
        histories, pres, sample_s = load_samples(args.samples)
        where = f"{sum(map(len, histories))} iterations of {len(histories)} conditions"
    else:
        history, sample_s = nominal_samples(args.urdf, args.iterations)
        histories, pres = [history], [None]
        where = f"{len(history)} iterations at the nominal hole"
    default = DynamicsConfig()
    rows = {str(t): replay(replace(default, em_tolerance=t), histories, pres)
            for t in [default.em_tolerance, *args.tolerances]}  # fmt: skip
    return {"where": where, "sample_s": sample_s, "rows": rows}


def measure_at(tree: Path | None, argv: list[str]) -> dict[str, Any]:
    """:func:`measure` in a new interpreter, on the package of ``tree`` (None: this one)."""
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    out = subprocess.run([sys.executable, __file__, *argv, "--json"], check=True,
                         capture_output=True, text=True, env=env)  # fmt: skip
    return dict(json.loads(out.stdout.splitlines()[-1]))


def fastest(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Each row's smallest time of each part over repeated measurements."""
    rows = {t: {**row, **{k: min(r["rows"][t][k] for r in results) for k in PARTS}}
            for t, row in results[0]["rows"].items()}  # fmt: skip
    return {**results[0], "rows": rows}


def print_rows(label: str, measured: dict[str, Any], tolerances: list[float], error_ref: float
               ) -> float:  # fmt: skip
    """One line per tolerance; returns the fit's CPU seconds at the default tolerance."""
    sample_s = measured["sample_s"]
    for tolerance in tolerances:
        row = measured["rows"][str(tolerance)]
        total = sum(row[k] for k in PARTS)
        ratios = "  ".join(f"{row[k] / sample_s:8.3f}" for k in PARTS)
        print(f"{label:10s} {tolerance:9.3g}  {total / sample_s:10.3f}  {ratios}  "
              f"{row['em_iterations']:6.1f}  {row['error'] / error_ref:13.6f}")  # fmt: skip
    default = measured["rows"][str(DynamicsConfig().em_tolerance)]
    return float(sum(default[k] for k in PARTS))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--tolerances", type=float, nargs="+", default=[0.05, 0.2, 1.0])
    parser.add_argument("--samples", nargs="+", default=None, help="local_trace.py sample files")
    parser.add_argument("--reference", default=None, help="git revision to measure alongside")
    parser.add_argument("--repeats", type=int, default=1, help="with --reference")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.json:
        print(json.dumps(measure(args)))
        return
    argv = ["--urdf", args.urdf, "--iterations", str(args.iterations), "--tolerances",
            *map(str, args.tolerances), *(["--samples", *args.samples] if args.samples else [])]  # fmt: skip
    default = str(DynamicsConfig().em_tolerance)
    if args.reference is None:
        this, reference = measure(args), None
    else:
        root = Path(__file__).resolve().parents[2]
        with tempfile.TemporaryDirectory() as tmp:
            tree = Path(tmp) / "reference"
            subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(tree),
                            args.reference], check=True, capture_output=True)  # fmt: skip
            try:
                pairs = [(measure_at(tree, argv), measure_at(None, argv))
                         for _ in range(args.repeats)]  # fmt: skip
            finally:
                subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force",
                                str(tree)], check=True, capture_output=True)  # fmt: skip
        reference = fastest([p[0] for p in pairs])
        this = fastest([p[1] for p in pairs])
    base = reference if reference is not None else this
    error_ref = base["rows"][default]["error"]
    print(f"{this['where']}; sampling {this['sample_s']:.2f} s CPU; ratios to it")
    print(
        "revision   tolerance  fit/sample   em       evaluate  regression  p_pre   "
        "EM its  error/default"
    )
    if reference is not None:
        before = print_rows(args.reference, reference, args.tolerances, error_ref)
    after = print_rows("this", this, args.tolerances, error_ref)
    if reference is not None:
        print(f"fit time at the default tolerance, this / {args.reference}: {after / before:.3f}")


if __name__ == "__main__":
    run(main)
