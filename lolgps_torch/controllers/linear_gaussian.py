"""Building linear-Gaussian controllers ``p(u_t | x_t) = N(K_t x_t + k_t, cov_t)``
(docs/ALGORITHM.md section 3)."""

from __future__ import annotations

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.types import LinearGaussian


def mix(p_pre: LinearGaussian, p_cur: LinearGaussian, alpha: Tensor | float) -> LinearGaussian:
    """The acting controller of paper eq. 6, ``p_act = alpha p_pre + (1 - alpha) p_cur``.

    K, k and cov are mixed linearly (keeps the exploration scale); differentiable in ``alpha``
    and in both controllers.

    :param p_pre: the linearised global policy. :param p_cur: the local controller.
    :param alpha: weight of ``p_pre`` in [0, 1], a float or a 0-d tensor.
    """
    beta = 1.0 - alpha
    return LinearGaussian(
        K=alpha * p_pre.K + beta * p_cur.K,
        k=alpha * p_pre.k + beta * p_cur.k,
        cov=alpha * p_pre.cov + beta * p_cur.cov,
    )


def hold_controller(
    T: int,
    dX: int,
    q_index: slice,
    qd_index: slice,
    q0: Tensor,
    kp: Tensor,
    kd: Tensor,
    variance: Tensor,
) -> LinearGaussian:
    """PD controller holding the start pose, ``u = -kp (q - q0) - kd qd + N(0, diag(variance))``.

    :param T: number of steps. :param dX: state size.
    :param q_index: where the joint angles ``q`` sit in the state.
    :param qd_index: where the joint velocities ``qd`` sit in the state.
    :param q0: pose to hold ``[dU]``. :param kp: position gains ``[dU]``.
    :param kd: velocity gains ``[dU]``. :param variance: action noise variance ``[dU]``.
    """
    dU = q0.shape[-1]
    for name, index in (("q_index", q_index), ("qd_index", qd_index)):
        if len(range(dX)[index]) != dU:
            raise LolgpsError(
                f"{name} {index} selects {len(range(dX)[index])} of {dX} states, "
                f"but q0 has {dU} joints"
            )
    K = torch.zeros(T, dU, dX, dtype=q0.dtype, device=q0.device)
    K[:, :, q_index] = -torch.diag(kp)
    K[:, :, qd_index] = -torch.diag(kd)
    k = (kp * q0).expand(T, dU).clone()
    cov = torch.diag(variance).expand(T, dU, dU).clone()
    return LinearGaussian(K=K, k=k, cov=cov)
