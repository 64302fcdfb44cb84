"""Dynamics fitting: GMM EM, the normal-inverse-Wishart prior and the per-step regression."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor
from torch.distributions import Categorical, MixtureSameFamily, MultivariateNormal

from lolgps_torch.dynamics import (
    DynamicsConfig,
    DynamicsFitter,
    GaussianMixture,
    GMMPrior,
    NIWPrior,
    gaussian_regression,
)
from lolgps_torch.dynamics import gmm as gmm_module
from lolgps_torch.dynamics.gmm import BOUND_SLACK, PRUNE_NATS, RESPONSIBILITY_FLOOR, _m_step
from lolgps_torch.errors import LolgpsError

DTYPE = torch.float64
LOG_2PI = math.log(2 * math.pi)


def _system(T: int, dX: int, dU: int, seed: int) -> tuple[Tensor, Tensor]:
    """A smoothly time-varying linear system: F ``[T-1, dX, dX+dU]``, f ``[T-1, dX]``."""
    g = torch.Generator().manual_seed(seed)
    scale = 0.1 / dX**0.5  # keeps the spectral radius of the perturbations near 0.1
    A0 = 0.8 * torch.eye(dX, dtype=DTYPE) + scale * torch.randn(dX, dX, generator=g, dtype=DTYPE)
    dA = scale * torch.randn(dX, dX, generator=g, dtype=DTYPE)
    B = 0.3 * torch.randn(dX, dU, generator=g, dtype=DTYPE)
    s = torch.linspace(0, 1, T - 1, dtype=DTYPE)[:, None, None]
    F = torch.cat([A0 + s * dA, B.expand(T - 1, dX, dU)], dim=2)
    f = 0.1 * torch.sin(6 * s[:, :, 0] + torch.arange(dX, dtype=DTYPE))
    return F, f


def _rollouts(
    F: Tensor, f: Tensor, N: int, dU: int, noise: float, seed: int
) -> tuple[Tensor, Tensor]:
    """N rollouts of the system under random actions around a per-batch drifting mean."""
    g = torch.Generator().manual_seed(seed)
    T, dX = F.shape[0] + 1, F.shape[1]
    u_mean = (
        torch.randn(dU, generator=g, dtype=DTYPE) * torch.linspace(0, 1, T, dtype=DTYPE)[:, None]
    )
    u = u_mean + torch.randn(N, T, dU, generator=g, dtype=DTYPE)
    x = [0.5 * torch.randn(N, dX, generator=g, dtype=DTYPE)]
    for t in range(T - 1):
        y = torch.cat([x[-1], u[:, t]], dim=1) @ F[t].T + f[t]
        x.append(y + noise * torch.randn(N, dX, generator=g, dtype=DTYPE))
    return torch.stack(x, dim=1), u


def _regressors(x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    return torch.cat([x[:, :-1], u[:, :-1]], dim=-1), x[:, 1:]


def _error(F_hat: Tensor, F: Tensor) -> float:
    """Mean over steps of the Frobenius error."""
    return float(torch.linalg.matrix_norm(F_hat - F).mean())


@pytest.mark.parametrize("use_prior", [False, True])
def test_fit_error_falls_with_samples(use_prior: bool) -> None:
    F, f = _system(T=10, dX=4, dU=2, seed=0)
    errors = []
    for N in (10, 40, 160):
        x, u = _rollouts(F, f, N, dU=2, noise=0.05, seed=N)
        dynamics = DynamicsFitter(DynamicsConfig(use_prior=use_prior)).update(x, u)
        assert dynamics.F.shape == F.shape and dynamics.f.shape == f.shape
        errors.append(_error(dynamics.F, F))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.5 * errors[0]
    assert errors[2] < 0.1


def test_regression_without_prior_is_least_squares() -> None:
    """With no prior and no regulariser the joint-Gaussian fit is least squares with intercept,
    and cov the (biased) residual covariance."""
    F, f = _system(T=6, dX=3, dU=2, seed=1)
    X, Y = _regressors(*_rollouts(F, f, 30, dU=2, noise=0.1, seed=2))
    F_hat, f_hat, cov = gaussian_regression(X, Y, None, sigma_reg=0.0)
    for t in range(X.shape[1]):
        design = torch.cat([X[:, t], torch.ones(30, 1, dtype=DTYPE)], dim=1)
        coef = torch.linalg.lstsq(design, Y[:, t]).solution  # [dA + 1, dB]
        torch.testing.assert_close(F_hat[t], coef[:-1].T)
        torch.testing.assert_close(f_hat[t], coef[-1])
        residual = Y[:, t] - design @ coef
        torch.testing.assert_close(cov[t], residual.T @ residual / 30)


def test_regression_with_prior_follows_the_map_formula() -> None:
    """Against the posterior of docs/ALGORITHM.md section 4 written out step by step."""
    N, T, dA, dB = 4, 3, 5, 3
    g = torch.Generator().manual_seed(7)
    X = torch.randn(N, T, dA, generator=g, dtype=DTYPE)
    Y = torch.randn(N, T, dB, generator=g, dtype=DTYPE)
    root = torch.randn(T, dA + dB, dA + dB, generator=g, dtype=DTYPE)
    prior = NIWPrior(
        mu0=torch.randn(T, dA + dB, generator=g, dtype=DTYPE),
        Phi=root @ root.mT + 0.1 * torch.eye(dA + dB, dtype=DTYPE),
        m=0.7,
        n0=1.3,
    )
    F_hat, f_hat, cov_hat = gaussian_regression(X, Y, prior, sigma_reg=1e-3)
    for t in range(T):
        z = torch.cat([X[:, t], Y[:, t]], dim=1)  # [N, D]
        mu = z.mean(0)
        S = (z - mu).T @ (z - mu) / N
        d = mu - prior.mu0[t]
        sigma = (N * S + prior.Phi[t] + N * 0.7 / (N + 0.7) * torch.outer(d, d)) / (N + 1.3)
        sigma[:dA, :dA] += 1e-3 * torch.eye(dA, dtype=DTYPE)
        F = sigma[dA:, :dA] @ torch.linalg.inv(sigma[:dA, :dA])
        torch.testing.assert_close(F_hat[t], F)
        torch.testing.assert_close(f_hat[t], mu[dA:] - F @ mu[:dA])
        torch.testing.assert_close(cov_hat[t], sigma[dA:, dA:] - F @ sigma[:dA, :dA] @ F.T)


def test_regression_with_consistent_prior_is_exact_on_noiseless_data() -> None:
    """Noiseless data and a prior that obey the same y = A x + c give F = A, f = c, cov = 0,
    even with fewer samples than regressors (the prior fills the missing directions)."""
    T, dX, dU, N = 5, 6, 3, 3
    F, f = _system(T=T, dX=dX, dU=dU, seed=3)
    X, Y = _regressors(*_rollouts(F, f, N, dU=dU, noise=0.0, seed=4))
    g = torch.Generator().manual_seed(5)
    root = torch.randn(T - 1, dX + dU, dX + dU, generator=g, dtype=DTYPE)
    M = root @ root.mT + torch.eye(dX + dU, dtype=DTYPE)  # prior covariance of x
    joint_map = torch.cat([torch.eye(dX + dU, dtype=DTYPE).expand(T - 1, -1, -1), F], dim=1)
    Phi = joint_map @ M @ joint_map.mT  # covariance of [x; A x + c]
    x_mean = torch.randn(T - 1, dX + dU, generator=g, dtype=DTYPE)
    mu0 = torch.cat([x_mean, (F @ x_mean[:, :, None]).squeeze(-1) + f], dim=1)
    prior = NIWPrior(mu0=mu0, Phi=Phi, m=1.0, n0=0.7)
    F_hat, f_hat, cov = gaussian_regression(X, Y, prior, sigma_reg=0.0)
    torch.testing.assert_close(F_hat, F, atol=1e-9, rtol=0)
    torch.testing.assert_close(f_hat, f, atol=1e-9, rtol=0)
    torch.testing.assert_close(cov, torch.zeros_like(cov), atol=1e-9, rtol=0)


def test_gmm_prior_beats_plain_regression_with_few_samples() -> None:
    T, dX, dU, N = 30, 12, 4, 5
    F, f = _system(T=T, dX=dX, dU=dU, seed=6)
    fitter = DynamicsFitter(DynamicsConfig(max_trajectories=20))
    for iteration in range(3):
        fitter.update(*_rollouts(F, f, N, dU=dU, noise=0.01, seed=10 + iteration))
    x, u = _rollouts(F, f, N, dU=dU, noise=0.01, seed=20)
    with_prior = _error(fitter.update(x, u).F, F)
    plain = _error(gaussian_regression(*_regressors(x, u))[0], F)
    assert with_prior < 0.5 * plain


def _three_clusters(seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """600 points from a known 3-component mixture in 3-D, plus a constant fourth coordinate
    (a degenerate direction where only the covariance regulariser keeps the clusters proper)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 5.0]], dtype=DTYPE)
    weights = torch.tensor([0.5, 0.3, 0.2], dtype=DTYPE)
    labels = torch.multinomial(weights, 600, replacement=True, generator=g)
    scales = torch.tensor([1.0, 0.5, 2.0], dtype=DTYPE)[labels, None]
    points = means[labels] + scales * torch.randn(600, 3, generator=g, dtype=DTYPE)
    return torch.cat([points, torch.ones(600, 1, dtype=DTYPE)], dim=1), means, weights


def test_em_never_decreases_the_objective() -> None:
    """Overlapping clusters fitted with too many components: EM works for dozens of iterations."""
    g = torch.Generator().manual_seed(0)
    means = torch.tensor([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 3.0, 1.0]], dtype=DTYPE)
    labels = torch.multinomial(torch.tensor([0.5, 0.3, 0.2]), 400, replacement=True, generator=g)
    points = means[labels] + torch.randn(400, 3, generator=g, dtype=DTYPE)
    points = torch.cat([points, torch.ones(400, 1, dtype=DTYPE)], dim=1)
    gmm = GaussianMixture(tolerance=1e-9, seed=1)
    history = gmm.fit(points, K=6)
    assert len(history) >= 10
    steps = torch.tensor(history).diff()
    assert bool((steps >= -1e-10 * abs(history[-1])).all()), steps
    assert history[-1] > history[0] + 100


def test_em_recovers_separated_means() -> None:
    points, means, weights = _three_clusters(seed=0)
    gmm = GaussianMixture(tolerance=1e-8, seed=1)
    history = gmm.fit(points, K=3)
    assert bool((torch.tensor(history).diff() >= -1e-10 * abs(history[-1])).all())
    assert gmm.means is not None and gmm.log_weights is not None
    order = torch.cdist(means, gmm.means[:, :3]).argmin(1)  # fitted cluster per true cluster
    assert sorted(order.tolist()) == [0, 1, 2]
    torch.testing.assert_close(gmm.means[order, :3], means, atol=0.3, rtol=0)
    torch.testing.assert_close(gmm.log_weights[order].exp(), weights, atol=0.05, rtol=0)


def test_m_step_is_the_per_cluster_m_step_of_the_floored_responsibilities() -> None:
    """The M-step, summed over each cluster's own points, equals the textbook per-cluster
    M-step with responsibilities at or below the floor set to 0, and the floor changes the
    covariances by less than 1e-12 of the unfloored ones."""
    g = torch.Generator().manual_seed(0)
    P, D, K, alpha = 300, 5, 4, 1e-3
    points = torch.randn(P, D, generator=g, dtype=DTYPE) * torch.tensor([1.0, 2, 3, 0.1, 10])
    points = points - points.mean(0)
    resp = torch.softmax(30.0 * torch.randn(P, K, generator=g, dtype=DTYPE), dim=1)
    soft = (resp > RESPONSIBILITY_FLOOR) & (resp < 0.5)
    assert bool((resp <= RESPONSIBILITY_FLOOR).any() and soft.any())  # both kinds present

    def textbook(r: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        counts = r.sum(0)
        means = (r.T @ points) / counts[:, None]
        covs = (
            torch.stack(
                [
                    ((points - means[k]) * r[:, k, None]).T @ (points - means[k])
                    + alpha * torch.eye(D, dtype=DTYPE)
                    for k in range(K)
                ]
            )
            / counts[:, None, None]
        )
        return torch.log(counts / counts.sum()), means, covs

    floored = torch.where(resp > RESPONSIBILITY_FLOOR, resp, 0.0)
    for got, expected in zip(_m_step(points, resp, alpha), textbook(floored), strict=True):
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(_m_step(points, resp, alpha)[2], textbook(resp)[2], rtol=1e-12,
                               atol=1e-12)  # fmt: skip


def _dense_log_joint(points: Tensor, log_weights: Tensor, means: Tensor, chol_inv: Tensor
                     ) -> Tensor:  # fmt: skip
    """Every ``log w_k + log N(z_p | mu_k, Sigma_k)``, cluster by cluster from ``C_k (z - mu_k)``."""
    D = points.shape[1]
    columns = []
    for k in range(means.shape[0]):
        white = (points - means[k]) @ chol_inv[k].T
        log_det = torch.diagonal(chol_inv[k]).log().sum()
        columns.append(log_weights[k] + log_det - 0.5 * (white.square().sum(1) + D * LOG_2PI))
    return torch.stack(columns, dim=1)


def _random_mixture(K: int, D: int, seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """Log-weights, means and Cholesky factors of the precisions of a random mixture."""
    g = torch.Generator().manual_seed(seed)
    log_weights = torch.log_softmax(torch.randn(K, generator=g, dtype=DTYPE), 0)
    means = 6.0 * torch.randn(K, D, generator=g, dtype=DTYPE)
    factors = torch.randn(K, D, D, generator=g, dtype=DTYPE) / D**0.5
    covs = factors @ factors.mT + 0.1 * torch.eye(D, dtype=DTYPE)
    eye = torch.eye(D, dtype=DTYPE).expand(K, D, D)
    chol_inv = torch.linalg.solve_triangular(torch.linalg.cholesky(covs), eye, upper=False)
    return log_weights, means, chol_inv


def test_e_step_leaves_out_only_clusters_50_nats_below_the_best() -> None:
    """The E-step's log-joint equals the per-cluster formula to 1e-12 wherever it is computed,
    is -inf only where that is more than 50 nats below the point's best cluster, and gives
    the same responsibilities to 1e-12."""
    log_weights, means, chol_inv = _random_mixture(K=8, D=9, seed=0)
    g = torch.Generator().manual_seed(1)
    labels = torch.randint(8, (500,), generator=g)
    points = means[labels] + 2.0 * torch.randn(500, 9, generator=g, dtype=DTYPE)
    got = gmm_module._log_joint(points, log_weights, means, chol_inv)
    expected = _dense_log_joint(points, log_weights, means, chol_inv)
    left_out = torch.isinf(got)
    assert bool(left_out.any() and (~left_out).any())  # both kinds present
    torch.testing.assert_close(got[~left_out], expected[~left_out], rtol=1e-12, atol=1e-12)
    best = expected.max(1, keepdim=True).values.expand_as(expected)
    assert bool((expected[left_out] < best[left_out] - PRUNE_NATS).all())
    torch.testing.assert_close(torch.softmax(got, 1), torch.softmax(expected, 1), rtol=0,
                               atol=1e-12)  # fmt: skip


def test_e_step_computes_every_cluster_of_a_point_its_bound_misleads() -> None:
    """A cluster whose leading coordinate matches the point (the highest bound) but that is far
    in the last one, and a cluster 20 standard deviations off in the leading coordinate (a
    bound too low to be a candidate): the point's best exact value then does not rule the
    second out, so all its clusters are computed and the second gets the point."""
    D = 4  # bounds from the first coordinate (m = 1)
    means = torch.zeros(2, D, dtype=DTYPE)
    means[0, 3], means[1, 0] = 1000.0, 20.0
    chol_inv = torch.eye(D, dtype=DTYPE).expand(2, D, D)
    log_weights = torch.log(torch.tensor([0.5, 0.5], dtype=DTYPE))
    points = torch.zeros(1, D, dtype=DTYPE)
    assert BOUND_SLACK < 0.5 * 20.0**2  # the far cluster is not a candidate by its bound
    got = gmm_module._log_joint(points, log_weights, means, chol_inv)
    torch.testing.assert_close(got, _dense_log_joint(points, log_weights, means, chol_inv),
                               rtol=1e-12, atol=0)  # fmt: skip
    assert float(torch.softmax(got, 1)[0, 1]) == 1.0


def test_gmm_log_likelihood_and_responsibilities_match_torch_distributions() -> None:
    points, _, _ = _three_clusters(seed=2)
    gmm = GaussianMixture(seed=0)
    gmm.fit(points, K=3)
    assert gmm.log_weights is not None and gmm.means is not None and gmm.covs is not None
    mixture = MixtureSameFamily(
        Categorical(logits=gmm.log_weights), MultivariateNormal(gmm.means, gmm.covs)
    )
    torch.testing.assert_close(gmm.log_likelihood(points), mixture.log_prob(points).sum())
    components = MultivariateNormal(gmm.means, gmm.covs).log_prob(points[:, None, :])
    expected = torch.softmax(components + gmm.log_weights, dim=1)
    torch.testing.assert_close(gmm.responsibilities(points), expected)


def test_gmm_is_deterministic_and_warm_starts() -> None:
    points, _, _ = _three_clusters(seed=3)
    first, second = GaussianMixture(seed=7), GaussianMixture(seed=7)
    history = first.fit(points, K=3)
    assert history == second.fit(points, K=3)
    assert first.means is not None and second.means is not None
    assert torch.equal(first.means, second.means)
    # Refitting the same data with the same K starts at the converged solution.
    warm = first.fit(points, K=3)
    assert len(warm) <= 2
    assert warm[0] >= history[-1] - 1e-9 * abs(history[-1])


def _counting_e_steps(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Record the number of points of every E-step's log-joint computation."""
    rows: list[int] = []
    original = gmm_module._log_joint

    def counted(points: Tensor, *args: Tensor) -> Tensor:
        rows.append(points.shape[0])
        return original(points, *args)

    monkeypatch.setattr(gmm_module, "_log_joint", counted)
    return rows


def test_warm_start_reuses_the_log_joint_of_the_rows_it_ended_on(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A window that drops its oldest 200 points and appends 200 new ones: the warm start's
    first E-step computes only the new rows, and the fit equals one that computes them all."""
    points, _, _ = _three_clusters(seed=4)
    first, window = points[:400], points[200:]
    reusing, recomputing = GaussianMixture(seed=3), GaussianMixture(seed=3)
    reusing.fit(first, K=3)
    recomputing.fit(first, K=3)
    recomputing._kept = None  # computes every row
    rows = _counting_e_steps(monkeypatch)
    history = reusing.fit(window, K=3)
    assert rows[0] == 200 and all(r == 400 for r in rows[1:])
    expected = recomputing.fit(window, K=3)
    assert len(history) == len(expected)
    torch.testing.assert_close(torch.tensor(history), torch.tensor(expected), rtol=1e-12, atol=0)
    assert reusing.means is not None and recomputing.means is not None
    torch.testing.assert_close(reusing.means, recomputing.means, rtol=1e-12, atol=1e-12)


def test_responsibilities_of_the_last_rows_come_from_the_fit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """After a converged fit, the responsibilities of its last points are read from its last
    E-step (no new computation) and equal freshly computed ones; other points are computed."""
    points, _, _ = _three_clusters(seed=5)
    gmm = GaussianMixture(seed=0)
    gmm.fit(points, K=3)
    rows = _counting_e_steps(monkeypatch)
    kept = gmm.responsibilities(points[-100:])
    assert rows == [0]
    other = points[:50] + 0.01
    fresh = gmm.responsibilities(other)
    assert rows == [0, 50]
    gmm._kept = None
    torch.testing.assert_close(kept, gmm.responsibilities(points[-100:]), rtol=1e-12, atol=1e-12)
    assert rows[-1] == 100
    torch.testing.assert_close(fresh, gmm.responsibilities(other), rtol=0, atol=0)


def test_a_fit_stopped_by_max_iterations_keeps_no_log_joint(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fit that ends on an M-step has no E-step at its final parameters: the next E-step
    computes every row."""
    points, _, _ = _three_clusters(seed=6)
    gmm = GaussianMixture(max_iterations=1, seed=0)
    gmm.fit(points, K=3)
    rows = _counting_e_steps(monkeypatch)
    gmm.responsibilities(points)
    gmm.fit(points, K=3)
    assert rows == [600, 600]


def test_moment_matching() -> None:
    points, _, _ = _three_clusters(seed=4)
    gmm = GaussianMixture(seed=0)
    gmm.fit(points, K=3)
    assert gmm.means is not None and gmm.covs is not None
    one_hot = torch.eye(3, dtype=DTYPE)
    mean, cov = gmm.moments(one_hot)
    torch.testing.assert_close(mean, gmm.means)
    torch.testing.assert_close(cov, gmm.covs)
    # Law of total covariance for a two-cluster mixture.
    w = torch.tensor([[0.25, 0.0, 0.75]], dtype=DTYPE)
    mean, cov = gmm.moments(w)
    mu_a, mu_c = gmm.means[0], gmm.means[2]
    expected_mean = 0.25 * mu_a + 0.75 * mu_c
    d = mu_a - mu_c
    expected_cov = 0.25 * gmm.covs[0] + 0.75 * gmm.covs[2] + 0.25 * 0.75 * torch.outer(d, d)
    torch.testing.assert_close(mean[0], expected_mean)
    torch.testing.assert_close(cov[0], expected_cov)


def test_gmm_prior_keeps_recent_trajectories_and_scales_pseudo_counts() -> None:
    T, dA, dB = 8, 3, 2
    prior = GMMPrior(max_trajectories=6, min_points_per_cluster=10, strength=2.0)
    g = torch.Generator().manual_seed(0)
    with pytest.raises(LolgpsError):
        prior.evaluate(torch.zeros(1, T, dA, dtype=DTYPE), torch.zeros(1, T, dB, dtype=DTYPE))
    for _ in range(3):
        X = torch.randn(4, T, dA, generator=g, dtype=DTYPE)
        prior.update(X, torch.randn(4, T, dB, generator=g, dtype=DTYPE))
    assert prior.data is not None and prior.data.shape == (6, T, dA + dB)
    assert torch.equal(prior.data[-4:, :, :dA], X)
    assert prior.gmm.K == prior.n_clusters(48) == 4
    niw = prior.evaluate(X, torch.randn(4, T, dB, generator=g, dtype=DTYPE))
    assert niw.mu0.shape == (T, dA + dB) and niw.Phi.shape == (T, dA + dB, dA + dB)
    assert niw.m == 2.0
    assert niw.n0 == pytest.approx(2.0 * (48 - 2 - 5) / 48)
    assert bool((torch.linalg.eigvalsh(niw.Phi) > 0).all())
    assert prior.n_clusters(10) == 2 and prior.n_clusters(10_000) == 20


def test_single_cluster_prior_is_the_sample_gaussian_of_stored_points() -> None:
    """With K = 1 the prior at every step is the mean and (regularised, biased) covariance of all
    stored points, with Phi scaled by the strength."""
    T, dA, dB = 6, 3, 2
    g = torch.Generator().manual_seed(1)
    prior = GMMPrior(min_clusters=1, max_clusters=1, strength=2.0, cov_reg=1e-6)
    X = torch.randn(5, T, dA, generator=g, dtype=DTYPE)
    Y = X[..., :dB] ** 2 + 0.1 * torch.randn(5, T, dB, generator=g, dtype=DTYPE)
    prior.update(X, Y)
    points = torch.cat([X, Y], dim=-1).reshape(-1, dA + dB)
    centred = points - points.mean(0)
    cov = centred.T @ centred / points.shape[0] + 1e-6 * torch.eye(dA + dB, dtype=DTYPE)
    niw = prior.evaluate(X[:2], Y[:2])
    torch.testing.assert_close(niw.mu0, points.mean(0).expand(T, -1))
    torch.testing.assert_close(niw.Phi, 2.0 * cov.expand(T, -1, -1))


def test_fitter_at_full_size() -> None:
    """The main use: 5 samples of T = 100 steps, dX = 26, dU = 7."""
    N, T, dX, dU = 5, 100, 26, 7
    F, f = _system(T=T, dX=dX, dU=dU, seed=8)
    fitter = DynamicsFitter()
    for iteration in range(2):
        x, u = _rollouts(F, f, N, dU=dU, noise=0.01, seed=30 + iteration)
        dynamics = fitter.update(x, u)
    assert dynamics.F.shape == (T - 1, dX, dX + dU)
    assert dynamics.f.shape == (T - 1, dX) and dynamics.cov.shape == (T - 1, dX, dX)
    assert dynamics.x0_mean.shape == (dX,) and dynamics.x0_cov.shape == (dX, dX)
    for tensor in dynamics:
        assert tensor.dtype == DTYPE and bool(tensor.isfinite().all())
    torch.testing.assert_close(dynamics.cov, dynamics.cov.mT)
    assert bool((torch.linalg.eigvalsh(dynamics.x0_cov) > 0).all())
    torch.testing.assert_close(dynamics.x0_mean, x[:, 0].mean(0))
    assert _error(dynamics.F, F) < 0.5 * float(torch.linalg.matrix_norm(F).mean())


def test_fitter_follows_input_dtype_and_validates_shapes() -> None:
    F, f = _system(T=12, dX=3, dU=2, seed=9)
    x, u = _rollouts(F, f, 6, dU=2, noise=0.01, seed=0)
    dynamics = DynamicsFitter(DynamicsConfig(min_points_per_cluster=10)).update(
        x.float(), u.float()
    )
    assert all(tensor.dtype == torch.float32 for tensor in dynamics)
    with pytest.raises(LolgpsError):
        DynamicsFitter().update(x, u[:, :-1])
