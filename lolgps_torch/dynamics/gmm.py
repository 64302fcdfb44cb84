"""Gaussian mixture model fitted by expectation-maximisation, in torch.

Layout: points are ``[P, D]`` (P points of dimension D); the mixture holds ``K`` clusters with
log-weights ``[K]``, means ``[K, D]`` and covariances ``[K, D, D]``. Everything follows the device
and dtype of the points it was fitted on.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError

RESPONSIBILITY_FLOOR = 1e-20  # the M-step treats smaller responsibilities as 0
PRUNE_NATS = 50.0  # a log-joint this far below a point's best is left out (-inf)
BOUND_SLACK = 60.0  # pairs whose upper bound is within this of a point's best bound are computed


class GaussianMixture:
    """Mixture ``p(z) = sum_k w_k N(z | mu_k, Sigma_k)`` fitted by (penalised) EM.

    E-step: ``r_pk = w_k N(z_p | mu_k, Sigma_k) / sum_j w_j N(z_p | mu_j, Sigma_j)``.
    M-step, with ``n_k = sum_p r_pk``:
        ``w_k = n_k / P``,  ``mu_k = sum_p r_pk z_p / n_k``,
        ``Sigma_k = [sum_p r_pk (z_p - mu_k)(z_p - mu_k)^T + alpha I] / n_k``,
        ``alpha = cov_reg * P / K``.
    The ``alpha`` term regularises the covariances: a cluster of average size ``P / K`` gets
    exactly ``cov_reg`` on its diagonal, smaller clusters get more (which stops collapse). It is
    the exact M-step of the penalised log-likelihood (an inverse-Wishart kernel on each Sigma_k)
        ``L(theta) = sum_p log sum_k w_k N(z_p | mu_k, Sigma_k) - alpha/2 sum_k tr(Sigma_k^{-1})``,
    so EM never decreases ``L`` (a fixed ``+cov_reg I`` would not be an M-step of any fixed
    objective, and ``L`` could then drop). ``fit`` returns ``L`` per iteration and stops once an
    iteration gains less than ``tolerance`` nats per point.

    Initialisation: warm start from the previous fit when K and D are unchanged; otherwise
    k-means++ seeding and a few Lloyd iterations on per-dimension standardised points, then one
    M-step on the hard assignments. Random choices use a ``torch.Generator`` seeded by ``seed``,
    so a sequence of fits is deterministic.

    Reuse: when ``fit`` stops by the tolerance, its last E-step was at the final parameters,
    and its log-joint ``[P, K]`` is kept with its points. A later E-step at those parameters
    (the warm start's first one, ``responsibilities``, ``log_likelihood``) takes the rows of
    points that continue the kept ones, ``z_new[:L] = z_kept[s:s+L]`` (as a window of recent
    trajectories that dropped its oldest and appended new ones), from it and computes only the
    others.

    :param cov_reg: covariance regulariser for a cluster of average size.
    :param max_iterations: maximum number of EM iterations per ``fit``.
    :param tolerance: stop when ``L`` improves by less than this many nats per point.
    :param kmeans_iterations: Lloyd iterations of the cold-start initialisation.
    :param seed: seed of the generator used by the cold-start initialisation.
    """

    def __init__(
        self,
        cov_reg: float = 1e-6,
        max_iterations: int = 100,
        tolerance: float = 1e-3,
        kmeans_iterations: int = 10,
        seed: int = 0,
    ) -> None:
        self.cov_reg = cov_reg
        self.max_iterations = max_iterations
        self.tolerance = tolerance
        self.kmeans_iterations = kmeans_iterations
        self._generator = torch.Generator().manual_seed(seed)
        self.log_weights: Tensor | None = None  # [K]
        self.means: Tensor | None = None  # [K, D]
        self.covs: Tensor | None = None  # [K, D, D]
        self._chol_inv: Tensor | None = None  # [K, D, D], L_k^{-1} with Sigma_k = L_k L_k^T
        self._kept: tuple[Tensor, Tensor] | None = None  # points [P, D], log-joint [P, K]

    @property
    def K(self) -> int:
        """Number of clusters (0 before the first fit)."""
        return 0 if self.means is None else int(self.means.shape[0])

    def fit(self, points: Tensor, K: int) -> list[float]:
        """Fit K clusters to ``points: [P, D]`` by EM.

        :return: the penalised log-likelihood ``L`` before each M-step (non-decreasing).
        """
        if points.ndim != 2 or points.shape[0] < 1:
            raise LolgpsError(f"GMM points must be [P, D] with P >= 1, got {tuple(points.shape)}")
        if K < 1:
            raise LolgpsError(f"GMM needs at least one cluster, got K={K}")
        P = points.shape[0]
        # EM runs on centred points so that the M-step's raw second moments do not cancel.
        shift = points.mean(0)  # [D]
        centred = points - shift
        warm = self.means is not None and self.means.shape == (K, points.shape[1])
        if warm:
            log_weights, means, covs = (p.to(points) for p in self._fitted()[:3])
            means = means - shift
        else:
            log_weights, means, covs = self._initialise(centred, K)
        chol_inv = _cholesky_inverse(covs)
        alpha = self.cov_reg * P / K
        history: list[float] = []
        converged = False
        reused = self._known_rows(points) if warm else points.new_empty(0, K)
        for _ in range(self.max_iterations):
            fresh = _log_joint(centred[len(reused) :], log_weights, means, chol_inv)
            log_joint = torch.cat([reused, fresh])  # [P, K]
            reused = points.new_empty(0, K)  # the first E-step only
            log_norm = torch.logsumexp(log_joint, dim=1)  # [P]
            penalty = 0.5 * alpha * chol_inv.square().sum()  # alpha/2 sum_k tr(Sigma_k^{-1})
            history.append(float(log_norm.sum() - penalty))
            if len(history) > 1 and history[-1] - history[-2] < self.tolerance * P:
                converged = True
                break
            resp = torch.exp(log_joint - log_norm[:, None])  # [P, K]
            log_weights, means, covs = _m_step(centred, resp, alpha)
            chol_inv = _cholesky_inverse(covs)
        self.log_weights, self.means, self.covs = log_weights, means + shift, covs
        self._chol_inv = chol_inv
        self._kept = (points.clone(), log_joint) if converged else None
        return history

    def log_likelihood(self, points: Tensor) -> Tensor:
        """``sum_p log p(z_p)`` for ``points: [P, D]`` (no penalty), a scalar tensor."""
        return torch.logsumexp(self._log_joint(points), dim=1).sum()

    def responsibilities(self, points: Tensor) -> Tensor:
        """Cluster posteriors ``r_pk = p(k | z_p)`` for ``points: [P, D]`` -> ``[P, K]``."""
        return torch.softmax(self._log_joint(points), dim=1)

    def moments(self, weights: Tensor) -> tuple[Tensor, Tensor]:
        """Moment-match the mixture re-weighted by ``weights: [..., K]`` (rows summing to one).

        ``mu = sum_k w_k mu_k``, ``Sigma = sum_k w_k [Sigma_k + (mu_k - mu)(mu_k - mu)^T]``.

        :return: mean ``[..., D]`` and covariance ``[..., D, D]``.
        """
        _, means, covs, _ = self._fitted()
        K, D = means.shape
        batch = weights.shape[:-1]
        w = weights.reshape(-1, K)  # [B, K]
        mean = w @ means  # [B, D]
        diff = means - mean[:, None, :]  # [B, K, D]
        within = (w @ covs.reshape(K, D * D)).view(-1, D, D)  # [B, D, D]
        cov = torch.baddbmm(within, (diff * w[:, :, None]).mT, diff)
        return mean.reshape(*batch, D), cov.reshape(*batch, D, D)

    def _fitted(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        if (
            self.log_weights is None
            or self.means is None
            or self.covs is None
            or self._chol_inv is None
        ):
            raise LolgpsError("the Gaussian mixture has not been fitted yet")
        return self.log_weights, self.means, self.covs, self._chol_inv

    def _log_joint(self, points: Tensor) -> Tensor:
        log_weights, means, _, chol_inv = self._fitted()
        known = self._known_rows(points)
        return torch.cat([known, _log_joint(points[len(known) :], log_weights, means, chol_inv)])

    def _known_rows(self, points: Tensor) -> Tensor:
        """The kept log-joint of the leading rows of ``points`` that continue the kept points
        from some row s on (``[L, K]``, L = 0 when none do)."""
        none = points.new_empty(0, self.K)
        if self._kept is None or len(points) == 0:
            return none
        kept, log_joint = self._kept
        if kept.shape[1] != points.shape[1] or kept.dtype != points.dtype:
            return none
        for start in (kept == points[0]).all(1).nonzero().flatten().tolist():
            length = min(len(kept) - start, len(points))
            if torch.equal(kept[start : start + length], points[:length]):
                return log_joint[start : start + length]
        return none

    def _initialise(self, points: Tensor, K: int) -> tuple[Tensor, Tensor, Tensor]:
        """k-means++ seeding and Lloyd iterations on standardised ``points`` (centred), then one
        M-step on the hard assignments."""
        P = points.shape[0]
        scale = points.std(0, correction=0).clamp_min(1e-12) if P > 1 else 1.0
        z = points / scale  # [P, D]
        first = int(torch.randint(P, (1,), generator=self._generator))
        centres = z[first : first + 1]  # [k, D], grows to [K, D]
        for _ in range(1, K):
            # D^2 sampling; the tiny floor keeps the draw defined when all points coincide.
            d2 = torch.cdist(z, centres).square().min(1).values + 1e-12  # [P]
            cdf = torch.cumsum(d2, 0)
            draw = torch.rand((1,), generator=self._generator, dtype=z.dtype).to(z.device)
            index = torch.searchsorted(cdf, draw * cdf[-1]).clamp_max(P - 1)
            centres = torch.cat([centres, z[index]])
        for _ in range(self.kmeans_iterations):
            assign = torch.cdist(z, centres).argmin(1)  # [P]
            sums = torch.zeros_like(centres).index_add_(0, assign, z)
            counts = torch.bincount(assign, minlength=K).to(z.dtype)[:, None]
            # An emptied cluster keeps its previous centre.
            centres = torch.where(counts > 0, sums / counts.clamp_min(1), centres)
        assign = torch.cdist(z, centres).argmin(1)
        resp = torch.nn.functional.one_hot(assign, K).to(points.dtype)  # [P, K]
        return _m_step(points, resp, self.cov_reg * P / K)


def _log_joint(points: Tensor, log_weights: Tensor, means: Tensor, chol_inv: Tensor) -> Tensor:
    """``log w_k + log N(z_p | mu_k, Sigma_k)`` -> ``[P, K]``, with ``Sigma_k^{-1} = C_k^T C_k``
    for ``C_k = chol_inv[k]`` lower triangular; ``-inf`` where it is more than ``PRUNE_NATS``
    below the point's best cluster (``r_pk < e^-50``: the responsibilities and the likelihood
    change by less than float64's rounding).

    Pruning: ``C_k`` is lower triangular, so the first m whitened coordinates depend on the
    first m coordinates of z only and, for m = ceil(D / 4),
        ``|C_k (z - mu_k)|^2 >= |C_k[:m, :m] (z[:m] - mu_k[:m])|^2``,
    an upper bound on each log-joint for ``(m / D)^2`` of the work. The exact value is computed,
    cluster by cluster, for the pairs whose bound is within ``BOUND_SLACK`` of the point's best
    bound; a point whose best exact value is not ``PRUNE_NATS`` above every left-out bound has
    all K computed.
    """
    P, D = points.shape
    K = means.shape[0]
    half_log_det_precision = torch.diagonal(chol_inv, dim1=-2, dim2=-1).log().sum(-1)  # [K]
    constant = log_weights + half_log_det_precision - 0.5 * D * math.log(2 * math.pi)  # [K]
    augmented = torch.cat([points, torch.ones_like(points[:, :1])], dim=1)  # [P, D + 1]
    operator = _whitening(means, chol_inv)  # [K, D, D + 1]
    m = -(-D // 4)
    lead = torch.cat([points[:, :m], augmented[:, D:]], dim=1)  # [P, m + 1]
    bound = constant - 0.5 * _mahalanobis(lead, _whitening(means[:, :m], chol_inv[:, :m, :m]))
    candidate = bound >= bound.max(1, keepdim=True).values - BOUND_SLACK  # [P, K]
    cluster, point = torch.nonzero(candidate.T, as_tuple=True)  # cluster by cluster
    rows = augmented[point].split(torch.bincount(cluster, minlength=K).tolist())
    white = torch.cat([row @ operator[k].T for k, row in enumerate(rows)])  # [pairs, D]
    log_joint = torch.full((P, K), -math.inf, dtype=points.dtype, device=points.device)
    log_joint[point, cluster] = constant[cluster] - 0.5 * white.square().sum(-1)
    best = log_joint.max(1, keepdim=True).values
    unsure = (~candidate & (bound > best - PRUNE_NATS)).any(1)  # [P]
    if bool(unsure.any()):
        log_joint[unsure] = constant - 0.5 * _mahalanobis(augmented[unsure], operator)
    return log_joint


def _whitening(means: Tensor, chol_inv: Tensor) -> Tensor:
    """``[C_k, -C_k mu_k]`` ``[K, D, D + 1]``: applied to ``[z; 1]`` it gives ``C_k (z - mu_k)``."""
    offset = (chol_inv @ means[:, :, None]).squeeze(-1)  # [K, D]
    return torch.cat([chol_inv, -offset[:, :, None]], dim=2)


def _mahalanobis(augmented: Tensor, operator: Tensor) -> Tensor:
    """``|C_k (z_p - mu_k)|^2`` ``[P, K]`` for all pairs, as one product of the augmented
    points ``[z_p; 1]`` ``[P, D + 1]`` with the stacked ``operator`` ``[K, D, D + 1]``."""
    P = augmented.shape[0]
    K, D, _ = operator.shape
    return (augmented @ operator.reshape(K * D, D + 1).T).view(P, K, D).square().sum(-1)


def _m_step(points: Tensor, resp: Tensor, alpha: float) -> tuple[Tensor, Tensor, Tensor]:
    """Log-weights ``[K]``, means ``[K, D]`` and covariances ``[K, D, D]`` from centred
    ``points: [P, D]`` and responsibilities ``resp: [P, K]`` (see :class:`GaussianMixture`).

    The M-step of the responsibilities with every ``r_pk <= RESPONSIBILITY_FLOOR`` set to 0:
    the mixture's points belong almost all to one cluster each, so the second moments are
    summed per cluster over its own points, ``sum_{p: r_pk > floor} r_pk z_p z_p^T``, about
    ``P D^2`` products in all instead of ``K P D^2``. Zeroing changes each ``n_k`` by at most
    ``1e-20 P`` and each second moment by at most ``1e-20 P max_p |z_p|^2`` in norm, far
    below ``alpha`` (a lower bound on the eigenvalues of ``n_k Sigma_k``) unless the points
    span ~1e6.
    The scatter comes from raw moments, ``sum_p r_pk z_p z_p^T - n_k mu_k mu_k^T``; its
    rounding error, about ``1e-16 n_k |z|^2``, stays far below ``alpha`` for centred points
    unless they span ~1e4 or more.
    """
    P, D = points.shape
    K = resp.shape[1]
    resp = torch.where(resp > RESPONSIBILITY_FLOOR, resp, 0.0)
    # A floor keeps an emptied cluster finite; its weight is ~0 so it stays inert.
    counts = resp.sum(0).clamp_min(1e-10 * P)  # [K]
    means = (resp.T @ points) / counts[:, None]  # [K, D]
    cluster, point = torch.nonzero(resp.T, as_tuple=True)  # the kept pairs, cluster by cluster
    rows = points[point]  # [kept, D]
    weighted = rows * resp[point, cluster][:, None]
    sizes = torch.bincount(cluster, minlength=K).tolist()
    second = torch.stack(
        [a.T @ b for a, b in zip(rows.split(sizes), weighted.split(sizes), strict=True)]
    )  # [K, D, D]
    scatter = second - counts[:, None, None] * means[:, :, None] * means[:, None, :]
    eye = torch.eye(D, dtype=points.dtype, device=points.device)
    covs = (scatter + alpha * eye) / counts[:, None, None]
    return torch.log(counts / counts.sum()), means, 0.5 * (covs + covs.mT)


def _cholesky_inverse(covs: Tensor) -> Tensor:
    """``L^{-1}`` for ``covs = L L^T``, ``[K, D, D]`` lower triangular."""
    chol, info = torch.linalg.cholesky_ex(covs)
    if bool(info.any()):
        raise LolgpsError(
            "a GMM covariance is not positive definite (points span too large a range, or "
            "contain inf/NaN); check the data or raise cov_reg"
        )
    eye = torch.eye(covs.shape[-1], dtype=covs.dtype, device=covs.device)
    return torch.linalg.solve_triangular(chol, eye.expand_as(covs), upper=False)
