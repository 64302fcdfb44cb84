"""Time the S-step's Adam loop (paper eq. 8) on the engines torch offers, on one synthetic batch.

    python scripts/research/sstep_engines.py [--rows 40000] [--steps 300] [--repeats 3]
                                             [--width 42] [--batch-size 512] [--dtype float32]
                                             [--plain]

Engines, each fitting the same policy (the gain head; ``--plain``: the plain MLP, as up to
aae6f53) from the same weights on the same minibatches:

- ``hand-written``: the backward pass and Adam on one flat weight vector that
  ``lolgps_torch.policy.sstep`` held up to aae6f53 (``FlatMLP``, ``Adam``), when the package on
  the path has them;
- ``functional``: ``torch.autograd.grad`` and torch's functional fused ``adam``, the package's
  engine (the ``torch.optim.Adam`` class imports torch._dynamo, about 2 s, in every process);
- ``autograd``: ``loss.backward()`` through :func:`lolgps_torch.policy.kl_loss`'s quadratic
  part and ``torch.optim.Adam`` (default, ``foreach=True`` and ``fused=True``);
- ``compile``: the same step under ``torch.compile`` (compile time reported separately);
- ``func``: ``torch.func.grad`` of a functional loss with ``torch.optim.Adam(foreach=True)``.

Engines are run in turn ``--repeats`` times (interleaved, so a loaded machine slows them
alike) and the best seconds per 1000 steps are printed, with the ratio to the fastest.
"""

from __future__ import annotations

import argparse
import importlib
import time
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor

from lolgps_torch.cli import run
from lolgps_torch.policy import GaussianPolicy, PolicyConfig
from lolgps_torch.policy.sstep import AdamMoments, adam_step, set_statistics
from lolgps_torch.types import DistillBatch

Step = Callable[[Tensor], None]
# the package's S-step module; before this engine choice it held the hand-written engine
SSTEP: Any = importlib.import_module("lolgps_torch.policy.sstep")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", type=int, default=40000)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--width", type=int, default=42)
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument("--dtype", choices=("float64", "float32"), default="float32")
    parser.add_argument("--plain", action="store_true", help="the plain MLP (no gain head)")
    return parser.parse_args()


def synthetic_batch(rows: int, dX: int, dU: int) -> DistillBatch:
    """Rows of a smooth nonlinear target with random SPD precisions."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(rows, dX, generator=g, dtype=torch.float64)
    A = torch.randn(dU, dX, generator=g, dtype=torch.float64)
    B = torch.randn(dU, dU, dU, generator=g, dtype=torch.float64)
    prec = B @ B.mT / dU + torch.eye(dU, dtype=torch.float64)
    mean = torch.tanh(x @ A.T)
    index = torch.randint(dU, (rows,), generator=g)
    has_pre = torch.ones(rows, dtype=torch.bool)
    return DistillBatch(x, mean, prec[index], mean.flip(0), prec[index].flip(0), has_pre)


def quadratic(mean: Tensor, target: Tensor, prec: Tensor) -> Tensor:
    """``1/2 mean_rows (mu - target)^T P (mu - target)``, by the S-step's own quadratic form."""
    return 0.5 * SSTEP._quadratic(mean - target, prec).mean()


def weights(policy: GaussianPolicy) -> list[Tensor]:
    return [w for w in policy.parameters() if w.requires_grad]


def autograd_engine(
    policy: GaussianPolicy,
    rows: tuple[Tensor, ...],
    foreach: bool | None = None,
    fused: bool | None = None,
) -> Step:
    x, target, prec = rows
    optimiser = torch.optim.Adam(weights(policy), lr=1e-3, foreach=foreach, fused=fused)

    def step(index: Tensor) -> None:
        optimiser.zero_grad(set_to_none=True)
        quadratic(policy(x[index]), target[index], prec[index]).backward()
        optimiser.step()

    return step


def functional_engine(policy: GaussianPolicy, rows: tuple[Tensor, ...]) -> Step:
    """``torch.autograd.grad`` and the package's :func:`adam_step` (torch's functional fused
    Adam), as the S-step runs them."""
    x, target, prec = rows
    params = weights(policy)
    moments = AdamMoments.zeros(params)

    def step(index: Tensor) -> None:
        loss = quadratic(policy(x[index]), target[index], prec[index])
        adam_step(params, list(torch.autograd.grad(loss, params)), moments, 1e-3)

    return step


def compiled_engine(policy: GaussianPolicy, rows: tuple[Tensor, ...]) -> tuple[Step, float]:
    x, target, prec = rows
    optimiser = torch.optim.Adam(weights(policy), lr=1e-3, foreach=True)

    @torch.compile(dynamic=False)
    def loss_of(xb: Tensor, tb: Tensor, pb: Tensor) -> Tensor:
        return quadratic(policy(xb), tb, pb)

    def step(index: Tensor) -> None:
        optimiser.zero_grad(set_to_none=True)
        loss_of(x[index], target[index], prec[index]).backward()
        optimiser.step()

    start = time.perf_counter()
    step(torch.zeros(x.shape[0] and BATCH[0], dtype=torch.long))
    return step, time.perf_counter() - start


def func_engine(policy: GaussianPolicy, rows: tuple[Tensor, ...]) -> Step:
    x, target, prec = rows
    params = {k: v for k, v in policy.named_parameters() if v.requires_grad}
    optimiser = torch.optim.Adam(params.values(), lr=1e-3, foreach=True)

    def loss_of(p: dict[str, Tensor], xb: Tensor, tb: Tensor, pb: Tensor) -> Tensor:
        return quadratic(torch.func.functional_call(policy, p, (xb,)), tb, pb)

    grad_of = torch.func.grad(loss_of)

    def step(index: Tensor) -> None:
        grads = grad_of(
            {k: v.detach() for k, v in params.items()}, x[index], target[index], prec[index]
        )
        for name, value in params.items():
            value.grad = grads[name]
        optimiser.step()

    return step


BATCH = [128]


def hand_engine(policy: GaussianPolicy, batch: DistillBatch) -> Step:
    """The hand-written backward pass and flat Adam of ``sstep`` (float64 only)."""
    sstep = SSTEP
    rows = sstep.loss_rows(policy, batch, 0.1)
    net = sstep.FlatMLP(policy.net)
    adam = sstep.Adam(net.flat)

    def step(index: Tensor) -> None:
        minibatch = sstep.Rows(*(field.index_select(0, index) for field in rows))
        activations = net.forward(minibatch.x)
        mean = torch.addcmul(policy.u_mean, activations[-1], policy.u_scale)
        _, grad_mean = sstep.minibatch_loss(mean, minibatch, 0.1)
        net.backward(activations, grad_mean * policy.u_scale)
        adam.step(net.flat, net.grad, 1e-3)

    return step


def main() -> None:
    args = parse_args()
    BATCH[0] = args.batch_size
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    dX, dU = 26, 7
    batch = synthetic_batch(args.rows, dX, dU)
    config = PolicyConfig(
        hidden_sizes=(args.width,) * 4, batch_size=args.batch_size, feedback=not args.plain
    )
    gen = torch.Generator().manual_seed(1)
    draws = torch.randint(args.rows, (args.steps, args.batch_size), generator=gen)

    def fresh() -> tuple[GaussianPolicy, tuple[Tensor, ...]]:
        policy = GaussianPolicy(dX, dU, config)
        set_statistics(policy, batch, 0.1)
        policy.to(dtype)
        x = batch.x.to(dtype)
        return policy, (x, batch.mean_cur.to(dtype), batch.prec_cur.to(dtype))

    compile_seconds: list[float] = []

    def compiled() -> Step:
        step, seconds = compiled_engine(*fresh())
        compile_seconds.append(seconds)
        return step

    engines: dict[str, Callable[[], Step]] = {
        "autograd, Adam": lambda: autograd_engine(*fresh()),
        "autograd, Adam foreach": lambda: autograd_engine(*fresh(), foreach=True),
        "autograd, Adam fused": lambda: autograd_engine(*fresh(), fused=True),
        "autograd, functional fused Adam": lambda: functional_engine(*fresh()),
        "torch.func, Adam foreach": lambda: func_engine(*fresh()),
        "torch.compile, Adam foreach": compiled,
    }
    if args.dtype == "float64" and args.plain and hasattr(SSTEP, "FlatMLP"):
        engines["hand-written"] = lambda: hand_engine(fresh()[0], batch)
    best: dict[str, float] = {}
    for _ in range(args.repeats):
        for name, make in engines.items():
            step = make()
            start = time.perf_counter()
            for index in draws:
                step(index)
            seconds = (time.perf_counter() - start) * 1000.0 / args.steps
            best[name] = min(best.get(name, float("inf")), seconds)
    fastest = min(best.values())
    for name, seconds in sorted(best.items(), key=lambda kv: kv[1]):
        print(f"{name:28s} {seconds:6.2f} s per 1000 steps  ({seconds / fastest:.2f}x the fastest)")
    if compile_seconds:
        print(f"torch.compile's first step (compilation): {min(compile_seconds):.1f} s")


if __name__ == "__main__":
    run(main)
