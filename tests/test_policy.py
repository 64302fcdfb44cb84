"""The global policy, its linearisation and the S-step, against independent answers."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch.distributions import MultivariateNormal, kl_divergence

from lolgps_torch.dynamics import GMMPrior
from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy import (
    GaussianPolicy,
    PolicyConfig,
    distill,
    kl_loss,
    linearize_policy,
    optimal_variance,
)
from lolgps_torch.policy.net import AdamDtype
from lolgps_torch.policy.sstep import (
    AdamMoments,
    _loop_rows,
    _quadratic,
    _row_constants,
    _row_quadratics,
    adam_step,
    cosine_rate,
    set_statistics,
)
from lolgps_torch.types import DistillBatch

F64 = torch.float64


def random_spd(n: int, *batch: int, generator: torch.Generator) -> torch.Tensor:
    """Random symmetric positive definite matrices ``[*batch, n, n]`` with eigenvalues ~0.5-3."""
    A = torch.randn(*batch, n, n, dtype=F64, generator=generator)
    return A @ A.mT / n + 0.5 * torch.eye(n, dtype=F64)


def random_batch(M: int, dX: int, dU: int, seed: int) -> DistillBatch:
    g = torch.Generator().manual_seed(seed)
    has_pre = torch.arange(M) % 3 != 0
    mask = has_pre[:, None]
    return DistillBatch(
        x=torch.randn(M, dX, dtype=F64, generator=g),
        mean_cur=torch.randn(M, dU, dtype=F64, generator=g),
        prec_cur=random_spd(dU, M, generator=g),
        mean_pre=torch.randn(M, dU, dtype=F64, generator=g) * mask,
        prec_pre=random_spd(dU, M, generator=g) * mask[:, :, None],
        has_pre=has_pre,
    )


def reference_loss(
    mean: torch.Tensor, cov: torch.Tensor, batch: DistillBatch, pre_weight: float = 1.0
) -> torch.Tensor:
    """Mean over rows of KL(pi || p_cur) + lambda has_pre KL(pi || p_pre), by
    torch.distributions."""
    pi = MultivariateNormal(mean, covariance_matrix=cov.expand(batch.M, -1, -1))
    cur = kl_divergence(pi, MultivariateNormal(batch.mean_cur, precision_matrix=batch.prec_cur))
    rows = batch.has_pre
    pi_pre = MultivariateNormal(mean[rows], covariance_matrix=cov.expand(int(rows.sum()), -1, -1))
    p_pre = MultivariateNormal(batch.mean_pre[rows], precision_matrix=batch.prec_pre[rows])
    return (cur.sum() + pre_weight * kl_divergence(pi_pre, p_pre).sum()) / batch.M


def test_kl_loss_matches_torch_distributions() -> None:
    g = torch.Generator().manual_seed(1)
    batch = random_batch(M=60, dX=4, dU=3, seed=0)
    mean = torch.randn(60, 3, dtype=F64, generator=g)
    cov = torch.diag(torch.rand(3, dtype=F64, generator=g) + 0.1)
    leaves = (batch.mean_cur, batch.prec_cur, batch.mean_pre)
    for leaf in (mean, *leaves):
        leaf.requires_grad_(True)
    got = kl_loss(mean, cov, batch)
    expected = reference_loss(mean, cov, batch)
    assert torch.allclose(got, expected, rtol=1e-12, atol=1e-12)
    # Differentiable in the policy mean and in the controllers' targets, like the reference.
    grads = torch.autograd.grad(got, (mean, *leaves))
    expected_grads = torch.autograd.grad(expected, (mean, *leaves))
    for grad, expected_grad in zip(grads, expected_grads, strict=True):
        assert torch.allclose(grad, expected_grad, rtol=1e-9, atol=1e-12)
    assert grads[3][~batch.has_pre].abs().max() == 0  # rows without p_pre ignore mean_pre


def test_kl_loss_full_policy_covariance() -> None:
    g = torch.Generator().manual_seed(2)
    batch = random_batch(M=20, dX=2, dU=4, seed=3)
    mean = torch.randn(20, 4, dtype=F64, generator=g)
    cov = random_spd(4, generator=g)
    assert torch.allclose(kl_loss(mean, cov, batch), reference_loss(mean, cov, batch), rtol=1e-12)


@pytest.mark.parametrize("pre_weight", [0.0, 0.3, 1.0])
def test_weighted_pre_term_matches_torch_distributions(pre_weight: float) -> None:
    g = torch.Generator().manual_seed(6)
    batch = random_batch(M=30, dX=3, dU=3, seed=7)
    mean = torch.randn(30, 3, dtype=F64, generator=g)
    cov = random_spd(3, generator=g)
    got = kl_loss(mean, cov, batch, pre_weight)
    assert torch.allclose(got, reference_loss(mean, cov, batch, pre_weight), rtol=1e-12)


@pytest.mark.parametrize("pre_weight", [0.0, 0.3, 1.0])
def test_optimal_variance_minimises_the_loss(pre_weight: float) -> None:
    batch = random_batch(M=200, dX=3, dU=3, seed=4)
    mean = torch.randn(200, 3, dtype=F64, generator=torch.Generator().manual_seed(5))
    variance = optimal_variance(batch, pre_weight)
    best = kl_loss(mean, torch.diag(variance), batch, pre_weight)
    for i in range(3):
        for factor in (0.97, 1.03):
            perturbed = variance.clone()
            perturbed[i] *= factor
            assert kl_loss(mean, torch.diag(perturbed), batch, pre_weight) > best + 1e-6
    # Stationary: the gradient of the loss in the variance vanishes there.
    v = variance.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(kl_loss(mean, torch.diag(v), batch, pre_weight), v)
    assert grad.abs().max() < 1e-12


def nonlinear_batch(
    M: int, seed: int, pre_weight: float = 1.0
) -> tuple[DistillBatch, torch.Tensor]:
    """A batch whose two targets are nonlinear in x (p_pre everywhere; fixed precisions, as at
    one time step), and the minimiser of the regression part with p_pre weighted by lambda,
    the precision-weighted average
    ``(P_cur + lambda P_pre)^{-1} (P_cur mu_cur + lambda P_pre mu_pre)`` ([M, dU])."""
    g = torch.Generator().manual_seed(seed)
    scale, shift = (
        torch.tensor([1.0, 5.0, 0.2], dtype=F64),
        torch.tensor([0.0, 3.0, -1.0], dtype=F64),
    )
    z = 2 * torch.rand(M, 3, dtype=F64, generator=g) - 1
    mean_cur = torch.stack([torch.sin(2 * z[:, 0]) + z[:, 1] * z[:, 2], torch.tanh(3 * z[:, 2])], 1)
    mean_pre = torch.stack([z[:, 0] ** 2, z[:, 1] - z[:, 0]], 1)
    prec_cur = random_spd(2, generator=g).expand(M, 2, 2)
    prec_pre = random_spd(2, generator=g).expand(M, 2, 2)
    weighted_pre = pre_weight * prec_pre
    rhs = (prec_cur @ mean_cur[:, :, None] + weighted_pre @ mean_pre[:, :, None]).squeeze(-1)
    target = torch.linalg.solve(prec_cur + weighted_pre, rhs)
    has_pre = torch.ones(M, dtype=torch.bool)
    return DistillBatch(z * scale + shift, mean_cur, prec_cur, mean_pre, prec_pre, has_pre), target


@pytest.mark.parametrize("pre_weight", [PolicyConfig().pre_weight, 1.0])  # default, paper
def test_distill_fits_a_nonlinear_target(pre_weight: float) -> None:
    batch, target = nonlinear_batch(M=3000, seed=6, pre_weight=pre_weight)
    config = PolicyConfig(steps=1500, batch_size=64, seed=0, pre_weight=pre_weight)
    policy = GaussianPolicy(3, 2, config)
    assert not policy.trained
    with torch.no_grad():
        initial = kl_loss(policy(batch.x), policy.covariance(), batch, pre_weight)
    history = distill(policy, batch)
    assert policy.trained and len(history) == config.steps
    variance = optimal_variance(batch, pre_weight)
    assert torch.equal(policy.variance, variance)
    with torch.no_grad():
        final = kl_loss(policy(batch.x), policy.covariance(), batch, pre_weight)
        floor = kl_loss(target, policy.covariance(), batch, pre_weight)  # the best any mean
        error = (policy(batch.x) - target).norm(dim=1).pow(2).mean().sqrt()
    assert final - floor < 0.01 * (initial - floor)
    assert error < 0.05 * target.std(0).norm()
    first, last = sum(history[:100]) / 100, sum(history[-100:]) / 100
    assert last - floor < 0.05 * (first - floor)


def test_distill_is_deterministic_for_a_seed() -> None:
    batch, _ = nonlinear_batch(M=500, seed=7)
    config = PolicyConfig(steps=60, seed=3)
    runs = []
    for _ in range(2):
        policy = GaussianPolicy(3, 2, config)
        history = distill(policy, batch, generator=torch.Generator().manual_seed(11))
        runs.append((history, policy(batch.x).detach()))
    assert runs[0][0] == runs[1][0]
    assert torch.equal(runs[0][1], runs[1][1])
    other = GaussianPolicy(3, 2, config)
    assert distill(other, batch, generator=torch.Generator().manual_seed(12)) != runs[0][0]


def test_distill_ignores_pre_targets_without_p_pre() -> None:
    batch, _ = nonlinear_batch(M=200, seed=8)
    absent = torch.arange(200) % 2 == 0
    batch = batch._replace(
        mean_pre=torch.where(absent[:, None], 0.0, batch.mean_pre),
        prec_pre=torch.where(absent[:, None, None], 0.0, batch.prec_pre),
        has_pre=~absent,
    )
    garbage = batch._replace(
        mean_pre=torch.where(absent[:, None], 1e6, batch.mean_pre),
        prec_pre=torch.where(absent[:, None, None], torch.nan, batch.prec_pre),
    )
    config = PolicyConfig(steps=20)
    clean, dirty = GaussianPolicy(3, 2, config), GaussianPolicy(3, 2, config)
    assert distill(clean, batch) == distill(dirty, garbage)


def test_distill_names_a_teacher_precision_that_is_not_positive_definite() -> None:
    """A singular p_cur precision is one error naming it, before any arithmetic uses it."""
    batch, _ = nonlinear_batch(M=10, seed=9)
    prec_cur = batch.prec_cur.clone()
    prec_cur[3] = 0.0
    with pytest.raises(LolgpsError, match="prec_cur is not positive definite"):
        distill(GaussianPolicy(3, 2), batch._replace(prec_cur=prec_cur))


def test_distill_rejects_an_empty_batch() -> None:
    batch, _ = nonlinear_batch(M=10, seed=9)
    with pytest.raises(LolgpsError, match="empty"):
        distill(GaussianPolicy(3, 2), DistillBatch(*(field[:0] for field in batch)))


def test_one_combined_quadratic_form_equals_the_two_on_real_precision_ranges() -> None:
    """The loop's one quadratic form per row plus its constant (:func:`_loop_rows`) equals the
    two terms of eq. 8 on the raw rows (:func:`_row_quadratics`) at any policy mean, with
    teacher precisions spanning about 1e-2 to 1e6 across joints (a heavy shoulder beside a light
    wrist) and rows with and without p_pre."""
    M, dX, dU = 400, 5, 4
    batch = random_batch(M=M, dX=dX, dU=dU, seed=31)
    spread = torch.tensor([1e-2, 1.0, 1e3, 1e6], dtype=F64).sqrt()  # precisions 1e-2 .. 1e6
    outer = spread[:, None] * spread[None, :]
    batch = batch._replace(
        mean_cur=batch.mean_cur / spread,
        mean_pre=batch.mean_pre / spread,
        prec_cur=batch.prec_cur * outer,
        prec_pre=batch.prec_pre * outer,
    )
    policy = GaussianPolicy(dX, dU, PolicyConfig(pre_weight=0.1))
    set_statistics(policy, batch, 0.1)
    rows = _loop_rows(policy, batch, 0.1, F64)
    for seed in range(3):
        mean = (
            batch.mean_cur
            + torch.randn(M, dU, dtype=F64, generator=torch.Generator().manual_seed(seed)) / spread
        )
        z, target, prec = rows.unpack(torch.arange(M), dX, dU)
        assert torch.allclose(z, (batch.x - policy.x_mean) / policy.x_std)
        unscaled = (mean - policy.u_mean) / policy.u_scale
        combined = 0.5 * _quadratic(unscaled - target, prec) + rows.constant
        assert torch.allclose(combined, _row_quadratics(mean, batch, 0.1), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    ("feedback", "adam_dtype", "rel"),
    [(False, "float64", 1e-10), (True, "float64", 1e-10), (True, "float32", 1e-5)],
)
def test_distill_matches_autograd_adam_on_kl_loss(
    feedback: bool, adam_dtype: AdamDtype, rel: float
) -> None:
    """The S-step against a plain float64 loop written from the loss on the raw rows:
    autograd through :func:`kl_loss`'s terms (per-row constants computed once),
    ``torch.optim.Adam`` and ``CosineAnnealingLR`` on the same minibatches, for the plain MLP
    and the feedback head. In float64 the S-step's change of units and its two quadratic forms
    combined into one (:func:`_loop_rows`) change nothing beyond rounding; in float32 it agrees
    to float32's rounding."""
    batch = random_batch(M=300, dX=4, dU=3, seed=16)
    config = PolicyConfig(
        hidden_sizes=(16, 16),
        steps=50,
        batch_size=32,
        pre_weight=0.3,
        feedback=feedback,
        adam_dtype=adam_dtype,
    )
    policy, reference = GaussianPolicy(4, 3, config), GaussianPolicy(4, 3, config)
    history = distill(policy, batch, generator=torch.Generator().manual_seed(17))
    set_statistics(reference, batch, config.pre_weight)
    assert not torch.equal(reference.u_scale, torch.ones(3, dtype=F64))
    weights = [w for w in reference.parameters() if w.requires_grad]
    optimiser = torch.optim.Adam(weights, lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimiser, T_max=config.steps, eta_min=0.05 * config.learning_rate
    )
    draws = torch.randint(300, (config.steps, 32), generator=torch.Generator().manual_seed(17))
    constants = _row_constants(reference.covariance(), batch, 0.3)  # [M], once, as distill does
    expected = []
    for rows in draws:
        minibatch = DistillBatch(*(field[rows] for field in batch))
        loss = (_row_quadratics(reference(minibatch.x), minibatch, 0.3) + constants[rows]).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        expected.append(loss.item())
    assert history == pytest.approx(expected, rel=rel)
    assert torch.allclose(policy(batch.x), reference(batch.x), rtol=100 * rel, atol=100 * rel)


def test_distill_is_the_same_in_any_torque_units() -> None:
    """Multiplying one joint's teacher means by c and its precisions by 1/c^2 (the same
    Gaussians in other torque units) multiplies that joint's policy mean by c and changes
    nothing else: the S-step treats a light wrist and a heavy shoulder alike."""
    batch = random_batch(M=200, dX=4, dU=3, seed=18)
    c = torch.tensor([1.0, 1e3, 1e-2], dtype=F64)
    scaled = batch._replace(
        mean_cur=batch.mean_cur * c,
        mean_pre=batch.mean_pre * c,
        prec_cur=batch.prec_cur / (c[:, None] * c[None, :]),
        prec_pre=batch.prec_pre / (c[:, None] * c[None, :]),
    )
    config = PolicyConfig(hidden_sizes=(16, 16), steps=100, batch_size=32)
    policy, other = GaussianPolicy(4, 3, config), GaussianPolicy(4, 3, config)
    distill(policy, batch)
    distill(other, scaled)
    assert torch.allclose(other(batch.x), policy(batch.x) * c, rtol=1e-8, atol=0.0)
    assert torch.allclose(other.variance, policy.variance * c**2, rtol=1e-12)


def test_whitening_floors_the_std() -> None:
    policy = GaussianPolicy(3, 1, PolicyConfig(std_floor=1e-3))
    x = torch.randn(100, 3, dtype=F64, generator=torch.Generator().manual_seed(0))
    x[:, 1] = 4.0
    policy.set_whitening(x)
    assert policy.x_std[1] == 1e-3 and policy.x_mean[1] == 4.0
    assert torch.allclose(policy.x_std[[0, 2]], x[:, [0, 2]].std(0, correction=0))
    assert torch.isfinite(policy(x)).all()


def linear_policy(dX: int, dU: int, seed: int) -> tuple[GaussianPolicy, torch.Tensor, torch.Tensor]:
    """A GaussianPolicy whose net is a linear map, and its affine law ``u = K x + k`` in raw x."""
    g = torch.Generator().manual_seed(seed)
    linear = torch.nn.Linear(dX, dU, dtype=F64)
    with torch.no_grad():
        linear.weight.copy_(torch.randn(dU, dX, dtype=F64, generator=g))
        linear.bias.copy_(torch.randn(dU, dtype=F64, generator=g))
    policy = GaussianPolicy(dX, dU, PolicyConfig(feedback=False))
    policy.net = torch.nn.Sequential(linear)
    policy.set_whitening(torch.randn(50, dX, dtype=F64, generator=g) * 2 + 1)
    policy.set_variance(torch.rand(dU, dtype=F64, generator=g) + 0.05)
    policy.trained = True
    K = linear.weight.detach() / policy.x_std
    return policy, K, linear.bias.detach() - K @ policy.x_mean


def test_linearize_recovers_a_linear_policy() -> None:
    dX, dU, N, T = 5, 3, 20, 6
    policy, K, k = linear_policy(dX, dU, seed=0)
    g = torch.Generator().manual_seed(1)
    drift = torch.linspace(0, 2, T, dtype=F64)[:, None]
    # States spread well beyond the 1e-6 regulariser of Sigma_xx, drifting over time.
    x = 3 * torch.randn(N, T, dX, dtype=F64, generator=g) + drift
    prior = GMMPrior()
    p_pre = linearize_policy(policy, x, prior)
    assert p_pre.K.shape == (T, dU, dX) and p_pre.cov.shape == (T, dU, dU)
    assert torch.allclose(p_pre.K, K.expand(T, -1, -1), atol=1e-6, rtol=0)
    assert torch.allclose(p_pre.k, k.expand(T, -1), atol=1e-6, rtol=0)
    # S_t = 0 up to the regularisers (1e-6) of the GMM and the regression.
    assert torch.allclose(p_pre.cov, policy.covariance().expand(T, -1, -1), atol=1e-5, rtol=0)
    assert prior.data is not None and prior.data.shape == (N, T, dX + dU)


def test_linearize_follows_a_nonlinear_policy_over_time() -> None:
    linear = torch.nn.Linear(2, 1, dtype=F64)
    with torch.no_grad():
        linear.weight.copy_(torch.tensor([[1.0, -0.5]], dtype=F64))
        linear.bias.zero_()
    policy = GaussianPolicy(2, 1, PolicyConfig(feedback=False))
    policy.net = torch.nn.Sequential(linear, torch.nn.Tanh())
    policy.set_variance(torch.tensor([0.3], dtype=F64))
    centres = torch.tensor([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [1.5, -1.0]], dtype=F64)
    N, T = 40, 4
    x = 0.05 * torch.randn(N, T, 2, dtype=F64, generator=torch.Generator().manual_seed(2)) + centres
    # A negligible prior and regulariser: the fit is then the per-step least-squares line.
    p_pre = linearize_policy(policy, x, GMMPrior(strength=1e-9), regression_reg=1e-12)
    u = policy(x).detach()  # [N, T, 1]
    design = torch.cat([x, torch.ones(N, T, 1, dtype=F64)], -1).transpose(0, 1)  # [T, N, 3]
    coef = torch.linalg.lstsq(design, u.transpose(0, 1)).solution  # [T, 3, 1]
    residual = u.transpose(0, 1) - design @ coef  # [T, N, 1]
    assert torch.allclose(p_pre.K, coef[:, :2].mT, atol=1e-6)
    assert torch.allclose(p_pre.k, coef[:, 2], atol=1e-6)
    assert torch.allclose(p_pre.cov, residual.mT @ residual / N + 0.3, atol=1e-6)
    # ... so each step's gain is the policy's Jacobian there, (1 - tanh^2(w.x)) w.
    w = torch.tensor([1.0, -0.5], dtype=F64)
    jacobian = (1 - torch.tanh(centres @ w) ** 2)[:, None, None] * w  # [T, 1, 2]
    assert torch.allclose(p_pre.K, jacobian, atol=0.01)


def test_kl_loss_rejects_an_indefinite_precision() -> None:
    batch = random_batch(M=4, dX=2, dU=2, seed=0)
    bad = batch._replace(
        prec_cur=batch.prec_cur * torch.tensor([1.0, -1.0, 1.0, 1.0])[:, None, None]
    )
    with pytest.raises(LolgpsError, match=r"prec_cur is not positive definite \(rows \[1\]"):
        kl_loss(batch.mean_cur, torch.eye(2, dtype=F64), bad)


def _panda_approach() -> DistillBatch:
    """A Panda's D_g during the approach: 12 stored successful samples of one condition of
    ``run_stream.py`` (pybullet_data panda.urdf, seed 2, commit aae6f53), steps 5-44, with
    their p_cur means and precisions (480 rows)."""
    stored = torch.load(Path(__file__).parent / "data" / "panda_dg_approach.pt")
    x, mean, prec = (stored[k].flatten(0, 1) for k in ("x", "mean_cur", "prec_cur"))
    none = torch.zeros(x.shape[0], dtype=torch.bool)
    return DistillBatch(x, mean, prec, torch.zeros_like(mean), torch.zeros_like(prec), none)


def _teacher_sds(policy: GaussianPolicy, batch: DistillBatch) -> float:
    """The mean fit error ``sqrt(d^T P_cur d)``, ``d = mu_theta(x) - mu_cur``, over the rows."""
    with torch.no_grad():
        d = (policy(batch.x) - batch.mean_cur).unsqueeze(-1)
    return float((d.mT @ batch.prec_cur @ d).flatten().sqrt().mean())


def test_gain_head_fits_a_high_gain_teacher() -> None:
    """The Panda's teachers vary by tens of their standard deviations between samples a few
    millimetres apart. 200 Adam steps of the default S-step (gain head) fit them to about 11 sd;
    the plain MLP (the S-step's net up to aae6f53) with the same steps stays near 19 sd."""
    batch = _panda_approach()
    errors = {}
    for feedback in (True, False):
        config = PolicyConfig(steps=200, feedback=feedback)
        policy = GaussianPolicy(batch.x.shape[1], batch.mean_cur.shape[1], config)
        distill(policy, batch)
        errors[feedback] = _teacher_sds(policy, batch)
    assert errors[True] < 12.5 < 16.0 < errors[False]


def test_adam_step_is_adam_written_out_and_the_rate_follows_its_cosine() -> None:
    """The S-step's Adam step against the update written out (Kingma and Ba, bias-corrected:
    ``m = b1 m + (1 - b1) g``, ``v = b2 v + (1 - b2) g^2``,
    ``w -= lr (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)``), over steps with changing
    gradients and rates; and the learning rate's cosine at its ends and its middle."""
    g = torch.Generator().manual_seed(0)
    weights = [torch.randn(4, 3, generator=g, dtype=torch.float64), torch.randn(3, generator=g, dtype=torch.float64)]  # fmt: skip
    mine = [w.clone() for w in weights]
    moments = AdamMoments.zeros(weights)
    m = [torch.zeros_like(w) for w in weights]
    v = [torch.zeros_like(w) for w in weights]
    for t in range(1, 6):
        grads = [torch.randn(w.shape, generator=g, dtype=torch.float64) for w in weights]
        lr = 0.01 * t
        adam_step(weights, grads, moments, lr)
        for i, grad in enumerate(grads):
            m[i] = 0.9 * m[i] + 0.1 * grad
            v[i] = 0.999 * v[i] + 0.001 * grad**2
            step = lr * (m[i] / (1 - 0.9**t)) / ((v[i] / (1 - 0.999**t)).sqrt() + 1e-8)
            mine[i] = mine[i] - step
    for got, want in zip(weights, mine, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    config = PolicyConfig(learning_rate=0.2, steps=100)
    assert cosine_rate(config, 0) == pytest.approx(0.2)
    assert cosine_rate(config, 50) == pytest.approx(0.5 * (0.2 + 0.01))
    assert cosine_rate(config, 100) == pytest.approx(0.01)


def test_net_output_is_the_modules_own_bit_for_bit() -> None:
    """The net applied as functions of its weights equals calling its modules, on one row
    (a control step) and on a batch, with and without the gain head."""
    gen = torch.Generator().manual_seed(3)
    for feedback in (True, False):
        policy = GaussianPolicy(9, 3, PolicyConfig(feedback=feedback, seed=4))
        with torch.no_grad():
            policy.gain.weight.normal_(generator=gen)
            policy.gain.bias.normal_(generator=gen)
        for rows in (1, 64):
            z = torch.randn(rows, 9, dtype=F64, generator=gen)
            h = policy.net[:-1](z)
            gain = policy.gain(h).unflatten(-1, (3, 9))
            expected = policy.net(z)
            if feedback:
                expected = policy.net[-1](h) + (gain * z.unsqueeze(-2)).sum(-1)
            assert torch.equal(policy.unscaled(z), expected)
