"""Temporally smoothed exploration noise for linear-Gaussian controllers (docs/ALGORITHM.md section 3).

    eps = W z,   z ~ N(0, I) along time,   W_ts = g(t - s) / ||g(t - .)||,
    g(d) = exp(-d^2 / 2 s^2)

Each row of the Gaussian filter W is scaled to unit norm, so every entry of ``eps`` is
exactly standard normal while neighbouring steps are correlated (lag-1 correlation about
exp(-1 / 4 s^2) away from the ends).  The original GPS renormalised by the empirical variance
of each rollout instead; the analytic scaling keeps the entries independent of the sample.
"""

from __future__ import annotations

import torch
from torch import Tensor


def smoothing_matrix(
    T: int, sigma_steps: float, dtype: torch.dtype, device: torch.device | str | None = None
) -> Tensor:
    """Row-normalised Gaussian filter ``W`` ``[T, T]`` applied along time.

    :param T: number of time steps.
    :param sigma_steps: standard deviation of the kernel in steps; ``<= 0`` gives the identity.
    """
    if sigma_steps <= 0.0:
        return torch.eye(T, dtype=dtype, device=device)
    t = torch.arange(T, dtype=dtype, device=device)
    W = torch.exp(-0.5 * ((t[:, None] - t[None, :]) / sigma_steps) ** 2)
    return W / torch.linalg.vector_norm(W, dim=1, keepdim=True)


def smoothed_noise(
    N: int,
    T: int,
    dU: int,
    sigma_steps: float = 2.0,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Tensor:
    """Standard normal noise ``[N, T, dU]`` smoothed along time, unit variance per entry.

    :param N: number of rollouts. :param T: number of steps. :param dU: action size.
    :param sigma_steps: kernel width in steps (2 as the original GPS); ``<= 0`` for white noise.
    :param generator: random generator for reproducible draws.
    """
    z = torch.randn(N, T, dU, generator=generator, dtype=dtype, device=device)
    W = smoothing_matrix(T, sigma_steps, dtype, device)
    return torch.einsum("ts,nsu->ntu", W, z)
