"""The S-step: distil the local controllers into the global policy (paper eq. 8).

    pi_theta <- argmin_theta  E_{x in D_g} [ KL(pi_theta(.|x) || p_cur(.|x))
                                             + lambda KL(pi_theta(.|x) || p_pre(.|x)) ]

lambda (``PolicyConfig.pre_weight``) is 1 in the paper.

Layout: rows are states flattened over samples and time, ``[M, ...]``.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

import torch
from torch import Tensor

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
    """``d_m^T P_m d_m`` for ``diff: [M, dU]``, ``prec: [M, dU, dU]`` -> ``[M]``."""
    return (diff.unsqueeze(-2) @ prec @ diff.unsqueeze(-1)).flatten()


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
def _intra_op_threads(n: int | None) -> Iterator[None]:
    """Run the body with ``n`` torch intra-op threads (None: unchanged), then restore."""
    previous = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class Rows(NamedTuple):
    """The batch as the Adam loop reads it: whitened states ``(x - x_mean) / x_std`` ``[M, dX]``,
    the targets with ``P_pre`` zeroed where there is no p_pre, and each row's constant part of
    the loss (:func:`_row_constants`), ``[M]``."""

    x: Tensor
    mean_cur: Tensor
    prec_cur: Tensor
    mean_pre: Tensor
    prec_pre: Tensor
    has_pre: Tensor
    constant: Tensor


def loss_rows(policy: GaussianPolicy, batch: DistillBatch, pre_weight: float) -> Rows:
    """The batch's :class:`Rows` for ``policy``'s whitening and ``Sigma_pi``."""
    x = (batch.x - policy.x_mean) / policy.x_std
    prec_pre = torch.where(batch.has_pre[:, None, None], batch.prec_pre, 0.0)
    constant = _row_constants(policy.covariance(), batch, pre_weight)
    return Rows(
        x, batch.mean_cur, batch.prec_cur, batch.mean_pre, prec_pre, batch.has_pre, constant
    )


def _quadratic_and_gradient(diff: Tensor, prec: Tensor, upstream: float) -> tuple[Tensor, Tensor]:
    """``s = (d^T P) d`` per row, ``[B]``, and ``g ds/dd = (g d^T) P^T + g (d^T P)^T``,
    ``[B, dU]``, for a scalar upstream gradient ``g``: the products autograd takes through
    :func:`_quadratic`, in its order (its ``[B, 1, 1]`` products with ``g`` are single
    multiplications, exact either way)."""
    row, column = diff.unsqueeze(-2), diff.unsqueeze(-1)  # [B, 1, dU], [B, dU, 1]
    left = row @ prec  # d^T P, [B, 1, dU]
    grad = (row * upstream) @ prec.mT + left * upstream  # [B, 1, dU]
    return (left @ column).flatten(), grad.squeeze(-2)


def minibatch_loss(mean: Tensor, rows: Rows, pre_weight: float) -> tuple[Tensor, Tensor]:
    """The minibatch loss of :func:`kl_loss`, ``L = 1/B sum_rows [const + 1/2 (d_cur^T P_cur
    d_cur + lambda has_pre d_pre^T P_pre d_pre)]`` with ``d = mu - mu_target``, and ``dL/dmu``
    ``[B, dU]``, in the arithmetic of ``loss.backward()`` through :func:`_row_quadratics`
    (so the S-step's results are bitwise those of autograd)."""
    scale = 1.0 / mean.shape[0] * 0.5  # d mean / d row, times the 1/2
    cur, grad_cur = _quadratic_and_gradient(mean - rows.mean_cur, rows.prec_cur, scale)
    has_pre = rows.has_pre[:, None]
    diff_pre = torch.where(has_pre, mean - rows.mean_pre, 0.0)
    pre, grad_pre = _quadratic_and_gradient(diff_pre, rows.prec_pre, scale * pre_weight)
    loss = (0.5 * (cur + pre_weight * pre) + rows.constant).mean()
    return loss, grad_cur + torch.where(has_pre, grad_pre, 0.0)


class FlatMLP:
    """The policy's ``Linear, ReLU, ..., Linear`` net with its weights in one flat vector and its
    gradient by hand (backpropagation), with no autograd graph:

        ``h_0 = x,  h_{l+1} = relu(h_l W_l^T + b_l),  mu = h_L W_L^T + b_L``;
        from ``g_L = dL/dmu``:  ``dL/dW_l = g_l^T h_l``,  ``dL/db_l = sum_rows g_l``,
        ``g_{l-1} = (g_l W_l) [h_l > 0]``.

    ``flat`` and ``grad`` are ``[n_weights]``; the layers' weights are views into them, so one
    optimiser update of ``flat`` updates every layer. :meth:`write_back` copies them to the net.
    """

    def __init__(self, net: torch.nn.Module) -> None:
        modules = list(net.children())
        kinds = [torch.nn.Linear if i % 2 == 0 else torch.nn.ReLU for i in range(len(modules))]
        if len(modules) % 2 == 0 or not all(map(isinstance, modules, kinds)):
            raise LolgpsError(f"the S-step needs a Linear, ReLU, ..., Linear net, got {net}")
        self.layers = [m for m in modules[0::2] if isinstance(m, torch.nn.Linear)]
        tensors = [t for layer in self.layers for t in (layer.weight, layer.bias)]
        self.flat = torch.cat([t.detach().flatten() for t in tensors])
        self.grad = torch.zeros_like(self.flat)
        params, grads, start = [], [], 0
        for t in tensors:
            params.append(self.flat[start : start + t.numel()].view_as(t))
            grads.append(self.grad[start : start + t.numel()].view_as(t))
            start += t.numel()
        self.weights, self.biases = params[0::2], params[1::2]
        self.weight_grads, self.bias_grads = grads[0::2], grads[1::2]

    def forward(self, x: Tensor) -> list[Tensor]:
        """The activations ``[h_0, ..., h_L, mu]`` at ``x: [B, dX]``."""
        activations = [x]
        last = len(self.weights) - 1
        for layer, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.addmm(bias, activations[-1], weight.t())
            activations.append(h if layer == last else h.relu_())
        return activations

    def backward(self, activations: list[Tensor], grad_mean: Tensor) -> None:
        """Fill ``grad`` from :meth:`forward`'s activations and ``dL/dmu: [B, dU]``."""
        g = grad_mean
        for layer in range(len(self.weights) - 1, -1, -1):
            h = activations[layer]
            torch.mm(g.t(), h, out=self.weight_grads[layer])
            torch.sum(g, 0, out=self.bias_grads[layer])
            if layer > 0:
                g = torch.ops.aten.threshold_backward(g.mm(self.weights[layer]), h, 0)

    def write_back(self) -> None:
        """Copy the flat weights into the net's parameters."""
        for layer, weight, bias in zip(self.layers, self.weights, self.biases, strict=True):
            layer.weight.copy_(weight)
            layer.bias.copy_(bias)


class Adam:
    """Adam with torch's defaults (``beta = (0.9, 0.999)``, ``eps = 1e-8``) and the arithmetic of
    ``torch.optim.Adam``, on one flat vector (one update for the whole net):

        ``m <- beta1 m + (1 - beta1) g``,  ``v <- beta2 v + (1 - beta2) g^2``,
        ``theta <- theta - lr_t / (1 - beta1^t) m / (sqrt(v) / sqrt(1 - beta2^t) + eps)``.
    """

    def __init__(self, like: Tensor, betas: tuple[float, float] = (0.9, 0.999)) -> None:
        self.m, self.v = torch.zeros_like(like), torch.zeros_like(like)
        self.betas, self.eps, self.t = betas, 1e-8, 0

    def step(self, theta: Tensor, grad: Tensor, rate: float) -> None:
        """Update ``theta`` in place from ``grad`` with learning rate ``rate``."""
        beta1, beta2 = self.betas
        self.t += 1
        self.m.lerp_(grad, 1 - beta1)
        self.v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        denom = (self.v.sqrt() / (1 - beta2**self.t) ** 0.5).add_(self.eps)
        theta.addcdiv_(self.m, denom, value=-rate / (1 - beta1**self.t))


def cosine_rates(config: PolicyConfig) -> list[float]:
    """Learning rate of each Adam step, a cosine from ``config.learning_rate`` down towards
    ``lr_min`` = 5% of it, ``lr_t = lr_min + (lr - lr_min) (1 + cos(pi t / steps)) / 2``, in the
    recursive form of ``torch.optim.lr_scheduler.CosineAnnealingLR`` (the same floats):
    ``lr_t = (1 + cos(pi t / steps)) / (1 + cos(pi (t - 1) / steps)) (lr_{t-1} - lr_min) + lr_min``.
    """
    rate, floor, steps = config.learning_rate, 0.05 * config.learning_rate, config.steps
    rates = [rate][:steps]
    for t in range(1, steps):
        ratio = (1 + math.cos(math.pi * t / steps)) / (1 + math.cos(math.pi * (t - 1) / steps))
        rates.append(ratio * (rates[-1] - floor) + floor)
    return rates


def distill(
    policy: GaussianPolicy,
    batch: DistillBatch,
    config: PolicyConfig | None = None,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Fit ``policy`` to the batch by minimising :func:`kl_loss` (paper eq. 8).

    Steps: whitening, ``Sigma_pi`` and output scaling from the batch (:func:`set_statistics`);
    each row's constant part of the loss (:class:`Rows`); then ``config.steps`` :class:`Adam`
    steps (fresh optimiser state, learning rate decayed along a cosine to 5% of
    ``config.learning_rate``, :func:`cosine_rates`) on minibatches of ``config.batch_size`` rows
    drawn uniformly with replacement, from the current weights (the policy keeps what earlier
    S-steps taught it), on ``config.num_threads`` intra-op threads. Only the precision-weighted
    regression term depends on theta; its gradient in ``mu`` (:func:`minibatch_loss`) is
    backpropagated by hand (:class:`FlatMLP`), with the products autograd would take, so the
    weights and losses are bitwise those of autograd, ``torch.optim.Adam`` and
    ``CosineAnnealingLR`` on :func:`kl_loss`, in ~1/4 of the time (no graph, one optimiser
    update for the whole net). The loss recorded per step is the full KL loss of that
    minibatch. Marks the policy trained. Deterministic for a given ``generator`` state.

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
    draws = torch.randint(batch.M, (config.steps, config.batch_size), generator=generator)
    history = batch.x.new_empty(config.steps)
    with _intra_op_threads(config.num_threads), torch.no_grad():
        rows_all = loss_rows(policy, batch, config.pre_weight)
        net = FlatMLP(policy.net)
        adam = Adam(net.flat)
        for step, (rows, rate) in enumerate(
            zip(draws.to(batch.x.device), cosine_rates(config), strict=True)
        ):
            minibatch = Rows(*(field.index_select(0, rows) for field in rows_all))
            activations = net.forward(minibatch.x)
            mean = torch.addcmul(policy.u_mean, activations[-1], policy.u_scale)
            loss, grad_mean = minibatch_loss(mean, minibatch, config.pre_weight)
            history[step] = loss
            net.backward(activations, grad_mean * policy.u_scale)
            adam.step(net.flat, net.grad, rate)
        net.write_back()
    policy.trained = True
    return history.tolist()
