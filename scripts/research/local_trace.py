"""One condition of a stream run, re-learnt as the stream learnt it, with the local learner's
internals per iteration (docs/ALGORITHM.md sections 3-5).

    python scripts/research/local_trace.py --run RUN --condition I [--iterations 25]
                                           [--config JSON]

RUN is a folder written by ``scripts/run_stream.py``: the task, the condition's offset and seed
and the stream's settings come from its config.json, and the global policy the condition
started from from the checkpoint after condition I-1 (none for condition 0), so the samples
are the stream's own (same seeds). ``--config`` overrides fields of the stream's settings
(JSON of ``StreamConfig`` fields, e.g. ``'{"local": {"cstep": {"kl_step": 0.5}}}'``).
Per iteration it prints:

- the samples' mean cost, success rate and mean final distance; the noiseless rollout's
  final distance of the new p_cur (``p_cur dist``);
- step_mult, epsilon, eta and the C-step's KL, and the KL to p_bar of the C-step's solution at
  the largest eta (``KL(eta_max)``, near 0 where the fit leads the C-step back to p_bar; above
  a tenth of epsilon the C-step keeps p_bar, :mod:`lolgps_torch.trajopt.cstep`);
- the step adaptation's three Laplace costs as improvements: ``pred`` = E[cost | p_prev, old
  model] - E[cost | p_act, old model] and ``act`` = E[cost | p_prev, old model] -
  E[cost | p_act, new model]; and the Monte-Carlo improvement of the sample costs;
- the one-step prediction error of the fit on the next iteration's samples (held out),
  ``mean |x_{t+1} - (F_t [x_t; u_t] + f_t)|^2``, as a ratio to its error on its own samples;
- the EM iterations of the dynamics' GMM update and its number of clusters K;
- the arm's reason for each sample it stopped at a limit (a line of its own);
- CPU seconds (one torch thread) of sampling, of ``LocalLearner.fit`` (GMM update, prior
  evaluation, regression, cost expansion, step adaptation), p_pre's fit and the C-step,
  summed at the end as ratios to sampling (the trace's own extra fit is counted apart).

``--save-samples`` keeps the samples, the run and condition, and the states p_pre was
linearised around at each iteration, for replaying the fits (``scripts/bench/bench_fit.py``).
The loop stops, as the stream's, after ``success_phases`` iterations with a success, or at
``--iterations``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import torch

from lolgps_torch.cli import run
from lolgps_torch.configs import from_dict
from lolgps_torch.controllers import mix, trajectory_kl
from lolgps_torch.cost.l12 import to_quadratic
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.dynamics import DynamicsFitter, prior_from_config
from lolgps_torch.dynamics import fit as fit_module
from lolgps_torch.dynamics.fit import gaussian_regression
from lolgps_torch.lolgps import local as local_module
from lolgps_torch.lolgps.local import Fit, LocalLearner
from lolgps_torch.lolgps.probes import noiseless_distance
from lolgps_torch.lolgps.run import read_run
from lolgps_torch.lolgps.stream import StreamConfig, condition_seed
from lolgps_torch.policy import linearize_policy
from lolgps_torch.sim.reflex import Reflex
from lolgps_torch.task import PegTask
from lolgps_torch.trajopt import CStepConfig, laplace_cost
from lolgps_torch.trajopt.lqr import augment, solve_with_retry, to_policy
from lolgps_torch.types import LinearDynamics, LinearGaussian, Trajectories


def one_step_error(dynamics: LinearDynamics, samples: Trajectories) -> float:
    """``mean_{n,t} |x_{t+1} - (F_t [x_t; u_t] + f_t)|^2`` over ``samples`` (t < T-1)."""
    xu = torch.cat([samples.x[:, :-1], samples.u[:, :-1]], dim=-1)
    predicted = torch.einsum("tij,ntj->nti", dynamics.F, xu) + dynamics.f
    return float((samples.x[:, 1:] - predicted).square().sum(-1).mean())


def kl_at_largest_eta(fit: Fit, p_bar: LinearGaussian, config: CStepConfig) -> float:
    """The trajectory KL to ``p_bar`` of the C-step's solution at ``config.eta_max`` on
    ``fit`` (NaN where its Quu is not positive definite there)."""
    eta = fit.cost.C.new_tensor([config.eta_max])
    problem = augment(fit.cost, fit.dynamics, p_bar)
    gain, factor, used, solved = solve_with_retry(problem, eta, config.pd_delta, config.eta_max)
    if not bool(solved.all()):
        return math.nan
    policy = LinearGaussian(*(part[0] for part in to_policy(gain, factor, used)))
    return float(trajectory_kl(policy, p_bar, fit.dynamics).sum())


def merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``override``'s fields replaced, nested dicts merged."""
    out = dict(base)
    for key, value in override.items():
        out[key] = merge(out[key], value) if isinstance(value, dict) else value
    return out


class Clock:
    """CPU seconds per named part; :meth:`wrap` times a function's calls under a name."""

    def __init__(self) -> None:
        self.parts: dict[str, float] = {}
        self.last = time.process_time()

    def lap(self, name: str) -> None:
        now = time.process_time()
        self.parts[name] = self.parts.get(name, 0.0) + now - self.last
        self.last = now

    def wrap(self, function: Callable[..., Any], name: str) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.process_time()
            out = function(*args, **kwargs)
            self.parts[name] = self.parts.get(name, 0.0) + time.process_time() - t0
            return out

        return timed


class Shadow:
    """A second fit of the learner's samples (its own :class:`DynamicsFitter`, same settings
    and seed, so the same models), for the step adaptation's improvements."""

    def __init__(self, learner: LocalLearner) -> None:
        self.learner = learner
        model = learner.task.model.linearize if learner.config.dynamics.prior == "model" else None
        self.fitter = DynamicsFitter(learner.config.dynamics, model)
        self.expand = learner.task.cost.expand
        self.dynamics: LinearDynamics | None = None  # the last samples' fit

    def improvements(self, p_act: LinearGaussian, samples: Trajectories) -> tuple[float, float]:
        """(pred, act) of the adaptation :meth:`LocalLearner.fit` is about to make."""
        last = self.learner.accepted
        dynamics = self.fitter.update(samples.x, samples.u)
        self.dynamics = dynamics
        if last is None:
            return float("nan"), float("nan")
        prev = last.fit
        expansion = self.expand(samples.x, samples.u, self.learner.targets)
        cost = to_quadratic(expansion, samples.x, samples.u)
        before = float(laplace_cost(prev.controller, prev.dynamics, prev.cost))
        return (
            before - float(laplace_cost(p_act, prev.dynamics, prev.cost)),
            before - float(laplace_cost(p_act, dynamics, cost)),
        )


def recorded_faults() -> list[str]:
    """The arm's reason for every rollout it stops at a limit from now on, in this process
    (:meth:`Reflex.violation` wrapped), in the list returned."""
    reasons: list[str] = []
    violation = Reflex.violation

    def recording(reflex: Reflex, q: Any, qd: Any, step: int) -> str | None:
        reason = violation(reflex, q, qd, step)
        if reason is not None:
            reasons.append(reason)
        return reason

    Reflex.violation = recording  # type: ignore[method-assign,assignment]
    return reasons


def print_stopped(reasons: list[str]) -> None:
    """A line per reason recorded (:func:`recorded_faults`); then forget them."""
    for reason in reasons:
        print(f"    a sample stopped: {reason}")
    reasons.clear()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--run", required=True)
    parser.add_argument("--condition", type=int, required=True)
    parser.add_argument("--iterations", type=int, default=None, help="default: the stream's")
    parser.add_argument("--config", default="{}", help="JSON overrides of StreamConfig")
    parser.add_argument(
        "--save-samples",
        default=None,
        help="write every iteration's samples, the states p_pre was linearised around and the "
        "sampling CPU time to this file (torch.save), for scripts/bench/bench_fit.py --samples",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    folder = RunFolder(args.run)
    info = read_run(folder)
    config = from_dict(StreamConfig, merge(asdict(info.stream), json.loads(args.config)))
    offset = info.conditions[args.condition]
    task = PegTask(info.task, n_worlds=config.local.samples)
    policy = None
    if args.condition > 0 and config.use_pre:
        policy = load_policy(folder.checkpoint_dir(args.condition - 1), task.device)
    learner = LocalLearner(
        task, offset, config.local, condition_seed(config, args.condition),
        limits=config.policy.limits(),
    )  # fmt: skip
    policy_prior = prior_from_config(config.local.dynamics)
    clock, shadow = Clock(), Shadow(learner)
    if learner.fitter.prior is not None:
        prior = learner.fitter.prior
        prior.update = clock.wrap(prior.update, "fit(): GMM update")  # type: ignore[method-assign]
        prior.evaluate = clock.wrap(prior.evaluate, "fit(): prior evaluation")  # type: ignore[method-assign]
    fit_module.gaussian_regression = clock.wrap(gaussian_regression, "fit(): regression")
    task.cost.expand = clock.wrap(task.cost.expand, "fit(): cost expansion")  # type: ignore[method-assign]
    local_module.laplace_cost = clock.wrap(laplace_cost, "fit(): step adaptation")
    stopped = recorded_faults()
    iterations = args.iterations or config.max_iterations
    p_pre: LinearGaussian | None = None
    history: list[Trajectories] = []
    accepted_x: list[torch.Tensor] = []  # the states p_pre was linearised around, per iteration
    alpha, phases = config.alpha, 0
    previous: tuple[LinearDynamics, Trajectories] | None = None  # the last samples and their fit
    print(f"condition {args.condition} at {offset}, {config.local}")
    print(" it  cost     succ  dist   p_cur dist  step_mult  eps     eta       KL      "
          "KL(eta_max)  pred      act       MC impr   EM its/K  1-step err (held-out / own)")  # fmt: skip
    for i in range(iterations):
        p_act = learner.p_cur if p_pre is None else mix(p_pre, learner.p_cur, alpha)
        clock.lap("other")
        samples = learner.sample(p_act)
        clock.lap("sampling")
        print_stopped(stopped)
        history.append(samples)
        clock.lap("other")
        pred, act = shadow.improvements(p_act, samples)
        clock.lap("trace only")
        if learner.planned_start_diverged(samples):  # as iterate(): the hold acts next
            print(f"{i:3d} {float(samples.cost.sum(1).mean()):8.2f}  the plan dropped for the hold")
            continue
        fit = learner.fit(p_act, samples)
        clock.lap("fit()")
        if policy is not None:
            assert learner.accepted is not None
            accepted_x.append(learner.accepted.x)
            p_pre = linearize_policy(policy, learner.accepted.x, policy_prior)
            clock.lap("p_pre fit")
        anchor = p_pre if p_pre is not None and config.cstep_anchor == "pre" else learner.p_cur
        clock.lap("other")
        reach = kl_at_largest_eta(fit, anchor, config.local.cstep)
        clock.lap("trace only")
        epsilon, eta, kl = learner.improve(fit, anchor)
        clock.lap("C-step")
        held_out = ""
        if previous is not None:
            held = one_step_error(previous[0], samples)
            own = one_step_error(*previous)
            held_out = f"{held:.3g} / {own:.3g}"
        mc = "" if previous is None else (
            f"{float(previous[1].cost.sum(1).mean() - samples.cost.sum(1).mean()):9.2f}")  # fmt: skip
        gmm = learner.fitter.prior.gmm if learner.fitter.prior is not None else None
        em = "" if gmm is None else f"{len(learner.fitter.em_history)}/{gmm.K}"
        dist = noiseless_distance(task, learner.p_cur, offset, learner.limits)
        clock.lap("other")
        print(
            f"{i:3d} {float(samples.cost.sum(1).mean()):8.2f} {float(samples.success.double().mean()):4.0%}"
            f"  {float(samples.final_distance.mean()):.3f}  {dist:.4f}      {learner.step_mult:6.3f}"
            f"  {epsilon:6.1f}  {eta:8.3g}  {kl:7.2f}  {reach:11.3g}  {pred:8.2f}  {act:8.2f}  {mc:>9}  {em:>8}  {held_out}",
            flush=True,
        )
        assert shadow.dynamics is not None
        previous = (shadow.dynamics, samples)
        alpha = config.next_alpha(alpha)
        phases += int(bool(samples.success.any()))
        if phases >= config.success_phases:
            break
    task.close()
    sample_s = clock.parts["sampling"]
    if args.save_samples is not None:
        saved = {"samples": [tuple(h) for h in history], "sample_s": sample_s,
                 "run": args.run, "condition": args.condition, "accepted_x": accepted_x}  # fmt: skip
        torch.save(saved, args.save_samples)
    print(
        "CPU seconds (ratio to sampling); fit() and its parts, p_pre's fit: the stream's time_fit"
    )
    for name, seconds in clock.parts.items():
        print(f"  {name:26s} {seconds:7.2f}  ({seconds / sample_s:.2f})")
    dynamics = sum(clock.parts.get(f"fit(): {n}", 0.0) for n in (
        "GMM update", "prior evaluation", "regression"))  # fmt: skip
    print(f"  {'dynamics fit alone':26s} {dynamics:7.2f}  ({dynamics / sample_s:.2f})")
    stream_fit = clock.parts["fit()"] + clock.parts.get("p_pre fit", 0.0)
    print(f"  {'time_fit (fit() + p_pre)':26s} {stream_fit:7.2f}  ({stream_fit / sample_s:.2f})")


if __name__ == "__main__":
    run(main)
