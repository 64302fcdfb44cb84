"""Planning through the acting mixture: the C-step's problem in terms of p_cur's own action.

Samples come from ``p_act = alpha p_pre + (1 - alpha) p_cur`` (paper eq. 6), so the action
applied is ``u = alpha (K_pre x + k_pre) + (1 - alpha) v`` with ``v`` drawn from p_cur. Solving
the C-step for ``v`` as if it were ``u`` makes p_cur plan for an arm it only half drives: with
alpha = 0.5 and a p_pre that heads for another hole, p_act never reaches this one. Rewriting
the fitted dynamics and cost in ``(x, v)`` lets the C-step optimise the acting controller
itself, while its KL bound still applies to p_cur.

With ``y = [x; u] = A_t [x; v] + b_t``, ``A_t = [[I, 0], [alpha K_pre_t, (1 - alpha) I]]`` and
``b_t = [0; alpha k_pre_t]``:
    dynamics  ``x' = F_t [x; u] + f_t = (F_t A_t) [x; v] + (f_t + F_t b_t)``,
    cost      ``C'_t = A_t^T C_t A_t``, ``c'_t = A_t^T (c_t + C_t b_t)``,
              ``cc'_t = cc_t + c_t^T b_t + 1/2 b_t^T C_t b_t``.
Plain torch, differentiable in alpha and in every input.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.types import LinearDynamics, LinearGaussian, QuadraticCost


def through_mixture(
    cost: QuadraticCost, dynamics: LinearDynamics, p_pre: LinearGaussian, alpha: Tensor | float
) -> tuple[QuadraticCost, LinearDynamics]:
    """Cost and dynamics of the C-step in ``(x, v)``, ``v`` being p_cur's action in p_act.

    :param cost: quadratic cost expansion in ``y = [x; u]``, ``[T, ...]``.
    :param dynamics: fitted dynamics in ``[x; u]``.
    :param p_pre: the linearised global policy mixed into p_act.
    :param alpha: p_pre's weight in p_act, in [0, 1).
    :return: the same cost and dynamics expressed in ``[x; v]``.
    """
    a = float(alpha)
    if not 0.0 <= a < 1.0:
        raise LolgpsError(f"planning through p_act needs alpha in [0, 1), got {a}")
    T, dU, dX = p_pre.K.shape
    dtype, device = p_pre.K.dtype, p_pre.K.device
    eye_x = torch.eye(dX, dtype=dtype, device=device).expand(T, dX, dX)
    eye_u = torch.eye(dU, dtype=dtype, device=device).expand(T, dU, dU)
    A = torch.cat(
        [
            torch.cat([eye_x, torch.zeros(T, dX, dU, dtype=dtype, device=device)], dim=-1),
            torch.cat([alpha * p_pre.K, (1.0 - alpha) * eye_u], dim=-1),
        ],
        dim=-2,
    )  # [T, dY, dY]
    b = torch.cat([torch.zeros(T, dX, dtype=dtype, device=device), alpha * p_pre.k], dim=-1)
    Cb = (cost.C @ b.unsqueeze(-1)).squeeze(-1)
    new_cost = QuadraticCost(
        C=A.mT @ cost.C @ A,
        c=(A.mT @ (cost.c + Cb).unsqueeze(-1)).squeeze(-1),
        cc=cost.cc + (cost.c * b).sum(-1) + 0.5 * (b * Cb).sum(-1),
    )
    F = dynamics.F
    new_dynamics = dynamics._replace(
        F=F @ A[:-1], f=dynamics.f + (F @ b[:-1].unsqueeze(-1)).squeeze(-1)
    )
    return new_cost, new_dynamics
