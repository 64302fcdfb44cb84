"""Learning-phase benchmarks, each a ratio to a reference measured in the same run.

    python scripts/bench/bench_learning.py [--urdf robots/kuka_peg.urdf] [--repeats 3]
        [--steps 3000] [--only NAME ...]

- sstep:    CPU time per Adam step of the S-step (``distill``) against its first formulation,
            kept here as the reference (autograd through two masked quadratic forms per row,
            ``torch.optim.Adam``, ``CosineAnnealingLR``), on the same batch (30 000 rows) and
            draws, alternated; and the largest relative difference of their loss histories.
- forms:    CPU time per step of the S-step's Adam loop as it runs (one packed gather and one
            quadratic form per row, ``_loop_rows``) against the same loop on the two forms of
            eq. 8 from six gathered fields (``_row_quadratics``, as ``kl_loss`` evaluates them),
            on the same rows in the net's units, draws and net, alternated; the paired ratio,
            and the largest relative difference of the two forms' row losses at the first step.
- replay:   the S-step with replay (``Distiller``: one new condition's D_g with its augmented
            copies, plus a replay of the earlier ones read from HDF5) for 8, 16 and 32
            conditions of the real sizes (9-45 successful rollouts of T = 100 steps each,
            the task's dX and dU), with the replay's rows and MB, and the time per S-step as a
            ratio to that at 8 conditions and to a condition's sampling (12 iterations of 5
            rollouts, the sampling of one iteration measured here).
- acting:   CPU time of one evaluation of the policy's mean on one row (a control step of a
            policy rollout) as ``GaussianPolicy.unscaled`` runs it (its layers applied as
            functions of their weights) against calling its modules, alternated, on ``--steps``
            states each; and whether the two give the same bits.
The figures are CPU times (``time.process_time``, one torch thread, PyBullet in-process);
medians over the repeats. The fit and C-step against the sampling of the same iteration are
``scripts/bench/bench.py --only algorithm``.
The cores are shared with other jobs: compare ratios, not seconds.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from typing import Any, TypeVar

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, initial_controller
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, distill, optimal_variance
from lolgps_torch.policy.sstep import (
    AdamMoments,
    _loop_rows,
    _quadratic,
    _row_constants,
    _row_quadratics,
    adam_step,
    set_statistics,
)
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import ConditionSamples, DistillBatch

F64 = torch.float64
ITERATIONS = 12  # iterations of a default-stream condition (11-14 in runs/lolgps-seed0)
R = TypeVar("R")


def reference_distill(
    policy: GaussianPolicy, batch: DistillBatch, config: PolicyConfig
) -> list[float]:
    """The S-step as first written (commit 8ba4168): per-row constants once, then per Adam step
    autograd through the two masked quadratic forms of ``_row_quadratics``, ``torch.optim.Adam``
    and ``CosineAnnealingLR``; the same minibatch draws as :func:`distill`."""
    generator = torch.Generator().manual_seed(config.seed)
    policy.set_whitening(batch.x)
    policy.set_variance(optimal_variance(batch, config.pre_weight))
    with torch.no_grad():
        constants = _row_constants(policy.covariance(), batch, config.pre_weight)  # [M]
    optimiser = torch.optim.Adam(policy.net.parameters(), lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimiser, T_max=config.steps, eta_min=0.05 * config.learning_rate
    )
    draws = torch.randint(batch.M, (config.steps, config.batch_size), generator=generator)
    history = []
    for rows in draws:
        minibatch = DistillBatch(*(field[rows] for field in batch))
        quadratics = _row_quadratics(policy(minibatch.x), minibatch, config.pre_weight)
        loss = (quadratics + constants[rows]).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        history.append(loss.item())
    return history


def cpu_time(fn: Callable[..., R], *args: Any, **kwargs: Any) -> tuple[float, R]:
    """``fn(*args, **kwargs)``'s CPU seconds and result."""
    t0 = time.process_time()
    out = fn(*args, **kwargs)
    return time.process_time() - t0, out


def random_precisions(n: int, dU: int, generator: torch.Generator) -> torch.Tensor:
    """``[n, dU, dU]`` symmetric positive definite, eigenvalues ~0.5-3."""
    A = torch.randn(n, dU, dU, dtype=F64, generator=generator)
    return A @ A.mT / dU + 0.5 * torch.eye(dU, dtype=F64)


def synthetic_condition(M: int, T: int, dX: int, dU: int, seed: int) -> ConditionSamples:
    """D_g of one condition: M rollouts of T steps; one precision per step (shared by the
    rollouts, as a linear-Gaussian controller's), targets smooth in x, a p_pre everywhere."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(M, T, dX, dtype=F64, generator=g)
    gain = torch.randn(dX, dU, dtype=F64, generator=g) / dX**0.5
    mean_cur = torch.tanh(x @ gain)
    mean_pre = mean_cur + 0.05 * torch.randn(M, T, dU, dtype=F64, generator=g)
    prec_cur = random_precisions(T, dU, g).expand(M, T, dU, dU).contiguous()
    prec_pre = random_precisions(T, dU, g).expand(M, T, dU, dU).contiguous()
    u = torch.zeros(M, T, dU, dtype=F64)
    cost, final = torch.zeros(M, T, dtype=F64), torch.zeros(M, dtype=F64)
    has_pre = torch.ones(M, dtype=torch.bool)
    return ConditionSamples(x, u, cost, final, mean_cur, prec_cur, mean_pre, prec_pre, has_pre)


def eight_conditions(task: PegTask) -> DistillBatch:
    """An 8-condition-sized S-step batch: 300 rollouts of the task's T steps, p_pre on two
    rows in three."""
    batch = synthetic_condition(300, task.T, task.layout.dX, task.layout.dU, seed=0)
    return batch._replace(has_pre=torch.arange(300) % 3 != 0).to_batch()


def bench_sstep(task: PegTask, repeats: int, steps: int) -> dict[str, float]:
    """CPU time per Adam step, plain against current S-step, on an 8-condition-sized batch."""
    dX, dU = task.layout.dX, task.layout.dU
    batch = eight_conditions(task)
    config = PolicyConfig(steps=steps)
    plain: list[float] = []
    fast: list[float] = []
    histories = []
    for _ in range(repeats):
        for fn, times in ((reference_distill, plain), (distill, fast)):
            took, history = cpu_time(fn, GaussianPolicy(dX, dU, config), batch, config)
            times.append(took / steps)
            histories.append(torch.tensor(history, dtype=F64))
    rel = ((histories[1] - histories[0]).abs() / histories[0].abs()).max()
    return {
        "rows": float(batch.M),
        "plain_ms_per_step": 1e3 * statistics.median(plain),
        "new_ms_per_step": 1e3 * statistics.median(fast),
        "speed_up": statistics.median(p / f for p, f in zip(plain, fast, strict=True)),
        "loss_max_rel_diff": float(rel),
    }


def bench_replay(task: PegTask, repeats: int, steps: int) -> dict[str, float]:
    """The S-step with replay at 8, 16 and 32 conditions; ratios to 8 and to sampling."""
    dX, dU, T = task.layout.dX, task.layout.dU, task.T
    learner = LocalLearner(task, (0.0, 0.0), LocalConfig(samples=len(task.sampler.worlds)), seed=0)
    sample = statistics.median(cpu_time(learner.sample, learner.p_cur)[0] for _ in range(3))
    sizes = torch.randint(9, 46, (32,), generator=torch.Generator().manual_seed(1)).tolist()
    config = PolicyConfig(steps=steps)
    labels = Labels(initial_controller(task, LocalConfig()), None, 0)
    results: dict[str, float] = {"sample_cpu_s": sample}
    with tempfile.TemporaryDirectory() as folder:
        replay = ReplayBuffer(RunFolder(folder).replay_path)
        reference = 0.0
        for index, M in enumerate(sizes):
            n = index + 1
            if n in (8, 16, 32):
                new = Labelled((0.0, 0.0), synthetic_condition(M, T, dX, dU, 1000 + n), labels)
                distiller = Distiller(task, config, 4, 2.0, replay)
                times = []
                for _ in range(repeats):
                    policy = GaussianPolicy(dX, dU, config)
                    times.append(cpu_time(distiller, policy, [new], seed=0)[0])
                took = statistics.median(times)
                reference = reference or took
                rows = sum(sizes[: n - 1]) * T
                results[f"{n}_replay_rows"] = float(rows)
                results[f"{n}_replay_MB"] = replay.path.stat().st_size / 1e6
                results[f"{n}_sstep_s"] = took
                results[f"{n}_over_8"] = took / reference
                results[f"{n}_over_cond_sampling"] = took / (ITERATIONS * sample)
            replay.append_condition(index, (0.0, 0.0), synthetic_condition(M, T, dX, dU, index), 1)
    return results


def bench_forms(task: PegTask, repeats: int, steps: int) -> dict[str, float]:
    """One quadratic form per row against two, in the Adam loop (module docstring)."""
    dX, dU = task.layout.dX, task.layout.dU
    batch = eight_conditions(task)
    config = PolicyConfig(steps=steps)
    policy = GaussianPolicy(dX, dU, config)
    set_statistics(policy, batch, config.pre_weight)
    one = _loop_rows(policy, batch, config.pre_weight, F64)
    scale = policy.u_scale
    outer = scale[:, None] * scale[None, :]
    two = DistillBatch(  # the same rows in the net's units, the two forms' fields apart
        (batch.x - policy.x_mean) / policy.x_std,
        (batch.mean_cur - policy.u_mean) / scale,
        batch.prec_cur * outer,
        (batch.mean_pre - policy.u_mean) / scale,
        torch.where(batch.has_pre[:, None, None], batch.prec_pre, 0.0) * outer,
        batch.has_pre,
    )
    draws = torch.randint(
        batch.M, (steps, config.batch_size), generator=torch.Generator().manual_seed(0)
    )

    def one_form(net: GaussianPolicy, index: torch.Tensor) -> torch.Tensor:
        z, target, prec = one.unpack(index, dX, dU)
        return 0.5 * _quadratic(net.unscaled(z) - target, prec)

    def two_forms(net: GaussianPolicy, index: torch.Tensor) -> torch.Tensor:
        rows = DistillBatch(*(field.index_select(0, index) for field in two))
        return _row_quadratics(net.unscaled(rows.x), rows, config.pre_weight)

    def loop(loss: Callable[[GaussianPolicy, torch.Tensor], torch.Tensor]) -> float:
        net = GaussianPolicy(dX, dU, config)
        weights: list[torch.Tensor] = [w for w in net.parameters() if w.requires_grad]
        moments = AdamMoments.zeros(weights)
        start = time.process_time()
        for index in draws:
            grads = list(torch.autograd.grad(loss(net, index).mean(), weights))
            adam_step(weights, grads, moments, config.learning_rate)
        return (time.process_time() - start) / steps

    first = GaussianPolicy(dX, dU, config)
    with torch.no_grad():  # equal up to the constant that one form leaves out
        reference = two_forms(first, draws[0])
        gap = one_form(first, draws[0]) + one.constant[draws[0]] - reference
    times = [(loop(two_forms), loop(one_form)) for _ in range(repeats)]
    return {
        "two_forms_ms_per_step": 1e3 * statistics.median(t for t, _ in times),
        "one_form_ms_per_step": 1e3 * statistics.median(o for _, o in times),
        "one / two (paired median)": statistics.median(o / t for t, o in times),
        "row_loss_max_rel_diff": float((gap.abs() / reference.abs()).max()),
    }


def bench_acting(task: PegTask, repeats: int, steps: int) -> dict[str, float]:
    """One-row evaluation of the policy, as applied against its modules called (module
    docstring)."""
    dX, dU = task.layout.dX, task.layout.dU
    policy = GaussianPolicy(dX, dU)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        policy.gain.weight.normal_(generator=gen)
    states = torch.randn(steps, 1, dX, dtype=F64, generator=gen)

    def called(z: torch.Tensor) -> torch.Tensor:
        h = policy.net[:-1](z)
        gain = policy.gain(h).unflatten(-1, (dU, dX))
        return policy.net[-1](h) + (gain * z.unsqueeze(-2)).sum(-1)

    def each(evaluate: Callable[[torch.Tensor], torch.Tensor]) -> float:
        start = time.process_time()
        for z in states:
            evaluate(z)
        return (time.process_time() - start) / steps

    with torch.no_grad():
        same = all(torch.equal(policy.unscaled(z), called(z)) for z in states[:100])
        times = [(each(called), each(policy.unscaled)) for _ in range(repeats)]
    return {
        "modules_called_us": 1e6 * statistics.median(c for c, _ in times),
        "as_applied_us": 1e6 * statistics.median(a for _, a in times),
        "applied / called (paired median)": statistics.median(a / c for c, a in times),
        "same bits": float(same),
    }


BENCHES = {
    "sstep": bench_sstep,
    "forms": bench_forms,
    "replay": bench_replay,
    "acting": bench_acting,
}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=PolicyConfig().steps, help="Adam steps")
    parser.add_argument("--only", nargs="*", choices=sorted(BENCHES), default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    task = PegTask(TaskConfig(urdf=args.urdf), n_worlds=5)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread")
    try:
        for name in args.only or BENCHES:
            results = BENCHES[name](task, args.repeats, args.steps)
            print(f"[{name}]")
            for key, value in results.items():
                print(f"  {key:<28}{value:12.4g}")
    finally:
        task.close()


if __name__ == "__main__":
    run(main)
