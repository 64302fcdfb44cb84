"""Typed records of a run, written as JSON with these field names as keys.

:class:`IterationRecord`, :class:`IdentifiedRecord` and :class:`DistillRecord` are the lines
of ``metrics.jsonl``;
:class:`ConditionSummary` is a condition's entry in ``summary.json`` (and its checkpoint's
``entry.json``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

from lolgps_torch.errors import LolgpsError


@dataclass(frozen=True)
class IterationRecord:
    """One iteration at one condition: its samples, its C-step and its phase times (s); the
    C-step time of iteration 0 includes the C-steps planned on the model before it."""

    condition: int
    iteration: int
    alpha: float
    mean_cost: float
    mean_distance: float
    best_distance: float
    success_rate: float
    faults: int
    epsilon: float
    eta: float
    kl: float
    step_mult: float
    time_sample: float
    time_fit: float
    time_cstep: float

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class IdentifiedRecord:
    """The arm identified at the start of a condition (``--identify``,
    :mod:`lolgps_torch.dynamics.identify`) and how well it predicts the condition's first
    rollouts, which the identification has not seen: the payload (kg) and its position in the
    last body's frame (m), the gravity compensation's gain κ and the share ρ of it that is the
    arm's own gravity rather than the URDF's, the links' mass scales, and the
    root-mean-square joint-velocity error (rad/s) of one control step predicted by the
    identified arm, by the URDF's and by the simulated arm's own (the model built from the
    true plant), over those rollouts' ``transitions`` free of contact."""

    condition: int
    payload: float
    payload_com: list[float]
    compensation: float
    mass_scale: list[float]
    error_identified: float
    error_urdf: float
    transitions: int
    error_plant: float = math.nan
    own_compensation: float = math.nan
    event: Literal["identified"] = "identified"

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class DistillRecord:
    """One S-step: after ``condition`` (the stream) or after ``iteration`` (batch GPS), its
    wall time (s) and, of it, the policy's rollouts' (its check and visits)."""

    condition: int
    time_distill: float
    distill_rows: int
    iteration: int | None = None
    repairs: int | None = None
    time_visits: float | None = None
    event: Literal["distilled"] = "distilled"

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass
class ConditionSummary:
    """What was learnt at one condition.

    :param iterations: iterations taken (rollouts = iterations x samples).
    :param first_success_iteration: the first iteration with a successful sample, if any.
    :param successful_samples: rollouts in the condition's D_g.
    :param local_final_distance: the noiseless final distance (m) of the local controller the
        condition ends with, the one that labels D_g (the final p_cur, unless its rollout
        misses; then the p_cur of the last iteration with successful samples).
    :param labels_from_iteration: the iteration whose p_cur labels D_g.
    :param policy_final_distance_after: the global policy's noiseless final distance (m)
        right after the condition's S-step; ``..._end`` after the whole stream (set last).
    :param distill_loss: the S-step's final loss (None without an S-step).
    :param rollouts: rollouts drawn at the condition.
    :param failure: why local learning stopped early on a numerical failure (None: it did
        not); the condition's D_g then holds the successes before it.
    :param repairs: S-step rounds run after the first fit (on the policy's own states, and
        while it missed a condition).
    :param policy_rollouts: the global policy's rollouts in the S-step (its check and visits).
    :param visited_rows: states the policy visited in the S-step that got a label.
    :param faults: rollouts drawn at the condition that the arm's controller stopped at a
        limit (counted as failures).
    :param arm_rollouts: the rollouts run on the arm for the condition, by kind: ``sample``
        (local learning), ``probe`` (noiseless checks of a controller or of the policy) and
        ``visit`` (the policy's rollouts in the S-step); empty in runs that did not count them.
    :param arm_faults: those of them the arm's controller stopped at a limit, by kind (empty
        in runs that did not count them).
    :param arm_seconds: a real arm's seconds for the condition, under torque command and
        moving to the start pose (None in a simulator).
    :param model_rollouts: the policy's rollouts on the arm's model instead of the arm (the
        S-step's visits with ``--visits model``), and ``model_faults`` those of them stopped at
        a limit.
    """

    condition: int
    offset: list[float]
    iterations: int
    first_success_iteration: int | None
    successful_samples: int
    local_final_distance: float
    local_success: bool
    labels_from_iteration: int
    policy_final_distance_after: float
    policy_success_after: bool
    distill_loss: float | None
    failure: str | None = None
    rollouts: int = 0
    repairs: int = 0
    policy_rollouts: int = 0
    visited_rows: int = 0
    faults: int = 0
    arm_rollouts: dict[str, int] = field(default_factory=dict)
    arm_faults: dict[str, int] = field(default_factory=dict)
    arm_seconds: float | None = None
    model_rollouts: int = 0
    model_faults: int = 0
    policy_final_distance_end: float | None = None
    policy_success_end: bool | None = None

    def to_json(self) -> dict[str, Any]:
        data = asdict(self)
        if self.policy_final_distance_end is None:  # not final yet: as in entry.json
            del data["policy_final_distance_end"], data["policy_success_end"]
        return data

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ConditionSummary:
        """Rebuild an entry read from disk; a missing or unknown key is a :class:`LolgpsError`."""
        names = {f.name for f in fields(cls)}
        try:
            return cls(**{k: v for k, v in data.items() if k in names})
        except TypeError as error:
            raise LolgpsError(f"corrupt summary entry: {error}") from None
