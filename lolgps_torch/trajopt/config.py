"""Settings of the C-step (docs/ALGORITHM.md section 5)."""

from __future__ import annotations

from dataclasses import dataclass

from lolgps_torch.errors import LolgpsError


@dataclass(frozen=True)
class CStepConfig:
    """KL step, step-size adaptation, dual search on eta and the PD retry of the C-step.

    :param kl_step: KL bound per time step at step_mult 1: ``epsilon = kl_step * step_mult * T``.
    :param step_mult_init: initial step multiplier.
    :param step_mult_min: lower bound of the step multiplier.
    :param step_mult_max: upper bound of the step multiplier (about 3 avoids overshooting after
        a first success, docs/ALGORITHM.md section 11).
    :param step_change_min: lower clip of one adaptation's factor on the multiplier.
    :param step_change_max: upper clip of one adaptation's factor on the multiplier.
    :param eta_min: smallest dual variable searched (the constraint is not binding below it).
    :param eta_max: largest dual variable; a candidate whose Quu is not positive definite
        even there leaves the dual search, and if every candidate does, it is an error.
        1e10, not the original's 1e16: with the scaled surrogate C + eta (-log p_bar), V's
        eta-sized terms nearly cancel, and past ~1e12 rounding amplified by unstable fitted
        dynamics makes Quu indefinite (seen on peg-insertion fits, on one also at 1e10 while
        smaller etas solved); by 1e10 p = p_bar anyway.
    :param kl_tolerance: accepted relative error ``|KL - epsilon| <= kl_tolerance * epsilon``.
    :param num_candidates: eta candidates evaluated together in one batched pass.
    :param max_passes: most batched passes of the dual search.
    :param pd_delta: first increment of eta when Quu is not positive definite (then doubling).
    :param pd_retry_width: doublings of that increment tried together in one batched retry.
    """

    kl_step: float = 1.0
    step_mult_init: float = 1.0
    step_mult_min: float = 0.01
    step_mult_max: float = 3.0
    step_change_min: float = 0.1
    step_change_max: float = 5.0
    eta_min: float = 1e-8
    eta_max: float = 1e10
    kl_tolerance: float = 0.1
    num_candidates: int = 8
    max_passes: int = 10
    pd_delta: float = 1e-4
    pd_retry_width: int = 8

    def __post_init__(self) -> None:
        if not 0.0 < self.eta_min < self.eta_max:
            raise LolgpsError(f"need 0 < eta_min < eta_max, got {self.eta_min}, {self.eta_max}")
        if not 0.0 < self.step_mult_min <= self.step_mult_init <= self.step_mult_max:
            raise LolgpsError(
                "need 0 < step_mult_min <= step_mult_init <= step_mult_max, got "
                f"{self.step_mult_min}, {self.step_mult_init}, {self.step_mult_max}"
            )
        if not 0.0 < self.step_change_min <= 1.0 <= self.step_change_max:
            raise LolgpsError("need 0 < step_change_min <= 1 <= step_change_max")
        if self.kl_step <= 0.0 or not 0.0 < self.kl_tolerance < 1.0:
            raise LolgpsError("need kl_step > 0 and 0 < kl_tolerance < 1")
        if self.num_candidates < 2 or self.max_passes < 1 or self.pd_retry_width < 1:
            raise LolgpsError("need num_candidates >= 2, max_passes >= 1, pd_retry_width >= 1")
        if self.pd_delta <= 0.0:
            raise LolgpsError(f"pd_delta must be positive, got {self.pd_delta}")
