"""The S-step: distil the local controllers into the global policy (paper eq. 8).

    pi_theta <- argmin_theta  E_{x in D_g} [ KL(pi_theta(.|x) || p_cur(.|x))
                                             + lambda KL(pi_theta(.|x) || p_pre(.|x)) ]

lambda (``PolicyConfig.pre_weight``) is 1 in the paper.

Layout: rows are states flattened over samples and time, ``[M, ...]``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

import torch
from torch import Tensor
from torch.optim.adam import adam

from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy.net import GaussianPolicy, PolicyConfig
from lolgps_torch.types import DistillBatch


def _check(batch: DistillBatch) -> None:
    M, dU = batch.mean_cur.shape
    shapes = {
        "x": (batch.x.shape[:1], (M,)),
        "prec_cur": (batch.prec_cur.shape, (M, dU, dU)),
        "mean_pre": (batch.mean_pre.shape, (M, dU)),
        "prec_pre": (batch.prec_pre.shape, (M, dU, dU)),
        "has_pre": (batch.has_pre.shape, (M,)),
    }
    for name, (got, want) in shapes.items():
        if tuple(got) != want:
            raise LolgpsError(f"distillation batch: {name} has shape {tuple(got)}, expected {want}")
    if M == 0:
        raise LolgpsError("distillation batch is empty: no successful samples to distil")


def _quadratic(diff: Tensor, prec: Tensor) -> Tensor:
    """``d_m^T P_m d_m`` for ``diff: [M, dU]``, ``prec: [M, dU, dU]`` -> ``[M]`` (as products
    and sums: on CPU a batched matmul of M tiny matrices costs more)."""
    return (diff * (prec * diff.unsqueeze(-2)).sum(-1)).sum(-1)


def _logdet_pd(matrix: Tensor, name: str) -> Tensor:
    """``log det A`` of symmetric positive definite ``A: [..., n, n]`` via its Cholesky factor."""
    chol, info = torch.linalg.cholesky_ex(matrix)
    if bool(info.any()):
        rows = info.nonzero().flatten().tolist()
        raise LolgpsError(f"{name} is not positive definite (rows {rows[:5]} ...)")
    return 2.0 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)


def _constant_terms(policy_cov: Tensor, prec: Tensor, name: str) -> Tensor:
    """The mean-independent part of ``KL(pi || p)``,
    ``1/2 [tr(P Sigma_pi) - dU - log det P - log det Sigma_pi]`` -> ``[M]``."""
    dU = policy_cov.shape[-1]
    trace = torch.einsum("mij,ji->m", prec, policy_cov)
    logdet_cov = _logdet_pd(policy_cov, "the policy covariance")
    return 0.5 * (trace - dU - _logdet_pd(prec, name) - logdet_cov)


def _row_constants(policy_cov: Tensor, batch: DistillBatch, pre_weight: float) -> Tensor:
    """Per-row constant part of the loss, ``[M]``; rows without p_pre get an identity
    precision in the masked-out term so the Cholesky factor exists."""
    eye = torch.eye(policy_cov.shape[-1], dtype=policy_cov.dtype, device=policy_cov.device)
    has_pre = batch.has_pre[:, None, None]
    prec_pre = torch.where(has_pre, batch.prec_pre, eye)
    pre = torch.where(batch.has_pre, _constant_terms(policy_cov, prec_pre, "prec_pre"), 0.0)
    return _constant_terms(policy_cov, batch.prec_cur, "prec_cur") + pre_weight * pre


def _row_quadratics(policy_mean: Tensor, batch: DistillBatch, pre_weight: float) -> Tensor:
    """Per-row precision-weighted regression part of the loss, ``1/2 [(mu - mu_cur)^T P_cur
    (mu - mu_cur) + lambda has_pre (mu - mu_pre)^T P_pre (mu - mu_pre)]``."""
    cur = _quadratic(policy_mean - batch.mean_cur, batch.prec_cur)
    # Masking the inputs (not the result) keeps values and gradients finite whatever the
    # ignored rows hold.
    diff_pre = torch.where(batch.has_pre[:, None], policy_mean - batch.mean_pre, 0.0)
    prec_pre = torch.where(batch.has_pre[:, None, None], batch.prec_pre, 0.0)
    pre = _quadratic(diff_pre, prec_pre)
    return 0.5 * (cur + pre_weight * pre)


def kl_loss(
    policy_mean: Tensor, policy_cov: Tensor, batch: DistillBatch, pre_weight: float = 1.0
) -> Tensor:
    """The S-step objective (paper eq. 8), averaged over rows:

        ``L = 1/M sum_m [KL(pi || p_cur) + lambda has_pre_m KL(pi || p_pre)]``, with
        ``KL(pi || p) = 1/2 [tr(P Sigma_pi) + (mu - mu_p)^T P (mu - mu_p) - dU
                             + log det Sigma_p - log det Sigma_pi]``

    and ``log det Sigma_p = -log det P``. Plain torch, differentiable in every input, the
    controllers' means and precisions included.

    :param policy_mean: ``mu_theta(x)`` at the batch's states, ``[M, dU]``.
    :param policy_cov: ``Sigma_pi``, ``[dU, dU]`` (diagonal for :class:`GaussianPolicy`).
    :param batch: states and controller Gaussians.
    :param pre_weight: lambda, the weight of the p_pre term (paper: 1).
    :return: scalar loss.
    """
    _check(batch)
    rows = _row_constants(policy_cov, batch, pre_weight) + _row_quadratics(
        policy_mean, batch, pre_weight
    )
    return rows.mean()


def optimal_variance(batch: DistillBatch, pre_weight: float = 1.0) -> Tensor:
    """Diagonal ``Sigma_pi = diag(sigma^2)`` minimising :func:`kl_loss`, ``[dU]``.

    The loss depends on ``sigma_i^2`` through ``1/2 sum_terms w (P_ii sigma_i^2 - log sigma_i^2)``;
    setting the derivative to zero gives
        ``sigma_i^2 = sum_terms w / sum_terms w P_ii`` (a weighted mean of ``P_ii``, inverted),
    where the terms are every row's ``P_cur`` (w = 1) and the ``P_pre`` of rows with
    ``has_pre`` (w = lambda).
    """
    _check(batch)
    diag_cur = batch.prec_cur.diagonal(dim1=-2, dim2=-1)  # [M, dU]
    diag_pre = torch.where(batch.has_pre[:, None], batch.prec_pre.diagonal(dim1=-2, dim2=-1), 0.0)
    n_terms = batch.M + pre_weight * batch.has_pre.to(diag_cur.dtype).sum()
    return n_terms / (diag_cur.sum(0) + pre_weight * diag_pre.sum(0))


def set_statistics(policy: GaussianPolicy, batch: DistillBatch, pre_weight: float) -> None:
    """The policy's fixed statistics for an S-step on ``batch``: the input whitening from its
    states, ``Sigma_pi`` in closed form (:func:`optimal_variance`), and the output scaling
    ``u_mean`` = the mean of the p_cur means, ``u_scale_j = max(std_j, sigma_j)``, the spread of
    joint j's p_cur means floored at the policy's own standard deviation.

    With the outputs scaled, the MLP's targets are O(1) on every joint, whatever the joint's
    torque units: the trained net is the same if one joint's torques are multiplied by c (its
    means by c, its precisions by 1/c^2). Without it, one joint whose teachers are very sure
    (a light distal link: precisions of 1e7 beside 20 on the shoulder) dominates the loss and
    the shared hidden layers, and the other joints are under-fitted.
    """
    policy.set_whitening(batch.x)
    policy.set_variance(optimal_variance(batch, pre_weight))
    spread = batch.mean_cur.std(0, correction=0)
    policy.set_output_scaling(batch.mean_cur.mean(0), spread.maximum(policy.variance.sqrt()))


@contextmanager
def intra_op_threads(n: int | None) -> Iterator[None]:
    """Run the body with ``n`` torch intra-op threads (None: unchanged), then restore."""
    previous = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class LoopRows(NamedTuple):
    """The rows as the Adam loop reads them (:func:`_loop_rows`): ``packed`` ``[M, dX + dU +
    dU^2]`` holds each row's whitened state, combined target and combined precision side by
    side (one gather per minibatch); ``constant`` ``[M]`` (float64) is the part of the
    quadratic terms that the combination leaves independent of theta."""

    packed: Tensor
    constant: Tensor

    def unpack(self, index: Tensor, dX: int, dU: int) -> tuple[Tensor, Tensor, Tensor]:
        """States ``[B, dX]``, targets ``[B, dU]`` and precisions ``[B, dU, dU]`` of the rows
        ``index``."""
        z, target, prec = self.packed.index_select(0, index).split((dX, dU, dU * dU), dim=1)
        return z, target, prec.unflatten(1, (dU, dU))


def _loop_rows(
    policy: GaussianPolicy, batch: DistillBatch, pre_weight: float, dtype: torch.dtype
) -> LoopRows:
    """The batch in the net's own units, its two quadratic terms combined into one.

    Units: states whitened, ``z = (x - x_mean) / x_std``; means scaled, ``(mu - u_mean) /
    u_scale``; precisions scaled, ``S P S`` with ``S = diag(u_scale)`` (the quadratic forms are
    invariant under this change of units, so the net's unscaled output stands for
    ``mu_theta``). Combination, per row, with ``A = P_cur``, ``B = has_pre P_pre``:

        ``(mu - a)^T A (mu - a) + lambda (mu - b)^T B (mu - b)
            = (mu - m)^T Q (mu - m) + (a - m)^T A (a - m) + lambda (b - m)^T B (b - m)``,
        ``Q = A + lambda B``, ``m = Q^-1 (A a + lambda B b)``

    (expand both sides with ``Q m = A a + lambda B b``), so the loop evaluates one quadratic
    form per row instead of two. Computed in float64 and then rounded to ``dtype``: every
    field is O(1) (the whitening resolves 1e-7 of a state's spread in float32,
    sub-micrometre for the peg)."""
    scale = policy.u_scale
    outer = scale[:, None] * scale[None, :]
    z = (batch.x - policy.x_mean) / policy.x_std
    a, b = (batch.mean_cur - policy.u_mean) / scale, (batch.mean_pre - policy.u_mean) / scale
    A = batch.prec_cur * outer
    B = torch.where(batch.has_pre[:, None, None], batch.prec_pre * outer, 0.0)
    b = torch.where(batch.has_pre[:, None], b, 0.0)
    Q = A + pre_weight * B
    m = torch.linalg.solve(Q, (A @ a.unsqueeze(-1) + pre_weight * B @ b.unsqueeze(-1)))
    m = m.squeeze(-1)
    constant = 0.5 * (_quadratic(a - m, A) + pre_weight * _quadratic(b - m, B))
    packed = torch.cat([z, m, Q.flatten(1)], dim=1).to(dtype)
    return LoopRows(packed, constant)


class AdamMoments(NamedTuple):
    """Adam's state for a list of weights: first and second moments, and step counts."""

    first: list[Tensor]
    second: list[Tensor]
    counts: list[Tensor]

    @classmethod
    def zeros(cls, weights: list[Tensor]) -> AdamMoments:
        """Fresh state: zero moments, no steps taken."""
        return cls(
            [torch.zeros_like(w) for w in weights],
            [torch.zeros_like(w) for w in weights],
            [torch.zeros((), dtype=torch.float32, device=w.device) for w in weights],
        )


def adam_step(weights: list[Tensor], grads: list[Tensor], moments: AdamMoments, lr: float) -> None:
    """One Adam step (betas 0.9 and 0.999, eps 1e-8) of ``weights`` in place, by torch's fused
    functional ``torch.optim.adam.adam``; ``moments`` advance with it. (The
    ``torch.optim.Adam`` class does the same arithmetic, but its first use imports
    torch._dynamo, about 2 s in every process.)"""
    with torch.no_grad():
        adam(
            weights, grads, moments.first, moments.second, [], moments.counts, fused=True,
            amsgrad=False, beta1=0.9, beta2=0.999, lr=lr, weight_decay=0.0, eps=1e-8,
            maximize=False,
        )  # fmt: skip


def cosine_rate(config: PolicyConfig, step: int) -> float:
    """Adam's learning rate at ``step`` of ``config.steps``, along a cosine from
    ``config.learning_rate`` to ``eta = 0.05 config.learning_rate``:
    ``eta + (lr - eta) (1 + cos(pi step / steps)) / 2``."""
    low = 0.05 * config.learning_rate
    return low + (config.learning_rate - low) * (1.0 + math.cos(math.pi * step / config.steps)) / 2


def distill(
    policy: GaussianPolicy,
    batch: DistillBatch,
    config: PolicyConfig | None = None,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Fit ``policy`` to the batch by minimising :func:`kl_loss` (paper eq. 8).

    Steps: whitening, ``Sigma_pi`` and output scaling from the batch (:func:`set_statistics`);
    each row's constant part of the loss (:func:`_row_constants`); then ``config.steps``
    Adam steps (:func:`adam_step`; fresh moments, learning rate decayed along a cosine to 5% of
    ``config.learning_rate``, :func:`cosine_rate`) on minibatches of ``config.batch_size``
    rows drawn
    uniformly with replacement, from the current weights (the policy keeps what earlier
    S-steps taught it), on ``config.num_threads`` intra-op threads. Only the precision-weighted
    regression term (:func:`_row_quadratics`) depends on theta; autograd differentiates it as
    one quadratic form per row, in the net's own units (:func:`_loop_rows`) and in
    ``config.adam_dtype``: a copy of the net in that type is trained and its weights are
    written back into the float64 policy. The loss
    recorded per step is the full KL loss of that minibatch. Marks the policy trained.
    Deterministic for a given ``generator`` state.

    :param policy: the global policy, trained in place.
    :param batch: successful states with their targets (detached here).
    :param config: training settings (default ``policy.config``).
    :param generator: source of the minibatch draws (default: seeded by ``config.seed``).
    :return: minibatch loss per Adam step, ``config.steps`` floats.
    """
    config = config if config is not None else policy.config
    generator = generator if generator is not None else torch.Generator().manual_seed(config.seed)
    _check(batch)
    batch = DistillBatch(*(field.detach() for field in batch))
    set_statistics(policy, batch, config.pre_weight)
    dtype = getattr(torch, config.adam_dtype)
    draws = torch.randint(batch.M, (config.steps, config.batch_size), generator=generator)
    draws = draws.to(batch.x.device)
    history: list[Tensor] = []
    trainee = copy.deepcopy(policy).to(dtype)
    weights: list[Tensor] = [w for w in trainee.parameters() if w.requires_grad]
    moments = AdamMoments.zeros(weights)
    net = trainee.layers()
    with intra_op_threads(config.num_threads):
        with torch.no_grad():
            constant = _row_constants(policy.covariance(), batch, config.pre_weight)  # checks P
            rows = _loop_rows(policy, batch, config.pre_weight, dtype)
            constant = constant + rows.constant
        for step, index in enumerate(draws):
            z, target, prec = rows.unpack(index, policy.dX, policy.dU)
            loss = 0.5 * _quadratic(net(z) - target, prec).mean()
            grads = list(torch.autograd.grad(loss, weights))
            adam_step(weights, grads, moments, cosine_rate(config, step))
            history.append(loss.detach())
    with torch.no_grad():
        for mine, trained in zip(policy.parameters(), trainee.parameters(), strict=True):
            mine.copy_(trained)
    policy.trained = True
    return (torch.stack(history).to(constant.dtype) + constant[draws].mean(1)).tolist()
