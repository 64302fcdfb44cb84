"""The global policy's own states, labelled by the teachers (docs/ALGORITHM.md section 7).

After an S-step the policy runs at every condition learnt so far: once without noise (the
closed-loop check) and ``noisy`` times with its own noise ``Sigma_pi``. A state ``x_t`` that it
visits at condition m is labelled by m's teachers, as D_g is: ``N(K_t x_t + k_t, cov_t)`` of
p_cur and p_pre. A time-varying linear-Gaussian controller is a local model, trustworthy only
near the states it was fitted and sampled at, so a state gets a label only inside the teacher's
support, within ``gate`` standard deviations of D_g(m)'s state marginal at t:

    g_t(x) = sqrt( 1/(2n) sum_{i in q, q-dot} ((x_i - mean_t,i) / max(std_t,i, floor_i))^2 )
    label x_t  iff  g_t(x_t) <= gate

(n joints; ``mean_t`` and ``std_t`` over D_g(m)'s samples; ``floor`` keeps a condition whose
samples barely differ from gating out every state). These rows join eq. 8's data, as DAgger
aggregates the states its learner reaches: the policy learns the teachers' corrections where its
own errors take it, not only where the teachers went.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from lolgps_torch.errors import NumericalError
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels, targets
from lolgps_torch.policy import GaussianPolicy, policy_actor
from lolgps_torch.state import StateLayout
from lolgps_torch.task import PegTask
from lolgps_torch.types import DistillBatch, Trajectories, VisitedRows


class Teacher(NamedTuple):
    """A learnt condition's index and hole offset, its controllers (None: not stored, so no
    state gets a label from it) and their support: D_g's per-step state mean and standard
    deviation, ``[T, dX]`` each, from its ``samples`` successful rollouts (0: no support)."""

    condition: int
    offset: tuple[float, float]
    labels: Labels | None
    mean: Tensor
    std: Tensor
    samples: int

    @classmethod
    def of(
        cls, condition: int, offset: tuple[float, float], x: Tensor, labels: Labels | None
    ) -> Teacher:
        """The teacher of a condition whose D_g has states ``x: [M, T, dX]``."""
        if x.shape[0] == 0:
            return cls(
                condition, offset, labels, x.new_zeros(x.shape[1:]), x.new_zeros(x.shape[1:]), 0
            )
        return cls(condition, offset, labels, x.mean(0), x.std(0, correction=0), int(x.shape[0]))


def support_distance(x: Tensor, teacher: Teacher, layout: StateLayout, floor: Tensor) -> Tensor:
    """``g_t(x)`` of the module docstring for states ``x: [N, T, dX]`` -> ``[N, T]``;
    ``floor: [dX]`` the smallest standard deviation per state entry."""
    z = (x - teacher.mean) / teacher.std.maximum(floor)
    return z[..., layout.q.start : layout.qd.stop].square().mean(-1).sqrt()  # q, q-dot


def gated_rows(
    x: Tensor, teacher: Teacher, labels: Labels, layout: StateLayout, gate: float, floor: Tensor
) -> VisitedRows:
    """The states of ``x: [N, T, dX]`` inside ``teacher``'s support, labelled by its
    controllers ``labels``."""
    inside = support_distance(x, teacher, layout, floor) <= gate  # [N, T]
    mean_cur, prec_cur, mean_pre, prec_pre, has_pre = targets(x, labels)
    t = torch.arange(x.shape[1], device=x.device).expand(x.shape[0], -1)
    rows = DistillBatch(
        x[inside],
        mean_cur[inside],
        prec_cur[inside],
        mean_pre[inside],
        prec_pre[inside],
        has_pre[:, None].expand_as(inside)[inside],
    )
    return VisitedRows(rows, torch.full_like(t[inside], teacher.condition), t[inside])


class Visit(NamedTuple):
    """One visit of the policy: its noiseless final distances (m) per teacher, the labelled
    rows (None: none), the rollouts it took and its wall time (s)."""

    distances: list[float]
    visited: VisitedRows | None
    rollouts: int
    seconds: float


VisitsOn = Literal["arm", "model"]


class PolicyVisits:
    """Rolls the policy out at the teachers' positions and labels the states it reaches.

    :param noisy: rollouts with the policy's own noise per position, besides the noiseless one.
    :param gate: the support radius, in D_g's per-step standard deviations (module docstring).
    :param floor: the smallest standard deviation of a joint angle (rad); the joint
        velocities' is ``10 floor`` (rad/s).
    :param on: where the policy is rolled out: on the arm, or on the arm's model
        (:meth:`~lolgps_torch.task.PegTask.simulate`), which costs the arm no rollout.
    """

    def __init__(
        self, task: PegTask, noisy: int, gate: float, floor: float, on: VisitsOn = "arm"
    ) -> None:
        self.task, self.noisy, self.gate, self.on = task, noisy, gate, on
        lay = task.layout
        self.floor = torch.zeros(lay.dX, dtype=torch.float64, device=task.device)
        self.floor[lay.q] = floor
        self.floor[lay.qd] = 10.0 * floor

    def __call__(
        self, policy: GaussianPolicy, teachers: Sequence[Teacher], seed: int, label: bool = True
    ) -> Visit:
        """One batch of rollouts: the noiseless one at every teacher's position, then (when
        ``label``) ``noisy`` noisy ones at each, their states labelled by their own position's
        teacher. A policy that blows the simulation up misses everywhere (distance inf) and
        gives no rows."""
        t0 = time.perf_counter()
        C, T, dU = len(teachers), self.task.T, self.task.layout.dU
        noisy = self.noisy if label else 0
        offsets = [teacher.offset for teacher in teachers] * (1 + noisy)
        gen = torch.Generator().manual_seed(seed)
        noise = torch.randn(C * noisy, T, dU, generator=gen, dtype=torch.float64)
        noise = torch.cat([noise.new_zeros(C, T, dU), noise]).to(self.task.device)
        actor = policy_actor(policy, self.task.model, noise)
        try:
            runs: Trajectories = (
                self.task.simulate(actor, offsets)
                if self.on == "model"
                else self.task.sample(actor, offsets, "visit")
            )
        except NumericalError:
            return Visit([math.inf] * C, None, len(offsets), time.perf_counter() - t0)
        parts = [
            gated_rows(
                runs.x[c::C], teacher, teacher.labels, self.task.layout, self.gate, self.floor
            )
            for c, teacher in enumerate(teachers)
            if label and teacher.labels is not None and teacher.samples > 0
        ]
        visited = VisitedRows.cat(parts) if parts else None
        distances = runs.scored_distance[:C].tolist()
        return Visit(distances, visited, len(offsets), time.perf_counter() - t0)


class Checked(NamedTuple):
    """A checked S-step: the kept round's losses, the kept policy's final distances (m) at
    every position learnt so far (NaN while untrained), the rounds run after the first fit,
    the labelled states the policy visited (None: none), the policy rollouts taken and their
    wall time (s)."""

    losses: list[float]
    distances: list[float]
    rounds: int
    visited: VisitedRows | None
    rollouts: int
    visit_seconds: float = 0.0


class CheckedSStep:
    """The S-step (eq. 8) on the policy's own states as well, checked in closed loop.

    After the first fit, the policy visits every position learnt so far (:class:`PolicyVisits`:
    the noiseless rollouts are the check; with ``label``, the states are labelled and kept,
    for this S-step's later rounds and, through the replay, for every later S-step). Then
    ``rounds`` rounds, and more while a position is missed (final distance not below
    ``threshold``) up to ``repairs`` in all, each of ``steps // 3`` Adam steps from the best
    policy so far on the data with every visited state so far, the missed conditions' D_g
    entering twice, followed by a visit. The policy reaching the most positions (then the
    smallest total distance) is kept.

    :param distill: the S-step with replay.
    :param visits: the policy's visits.
    :param threshold: the success distance (m).
    :param label: label and keep the visited states (off: the check alone).
    :param rounds: rounds always run (0: none).
    :param repairs: the most rounds while the policy misses (0 with ``rounds`` 0: the S-step
        alone, as in the paper).
    """

    def __init__(
        self,
        distill: Distiller,
        visits: PolicyVisits,
        threshold: float,
        label: bool,
        rounds: int,
        repairs: int,
    ) -> None:
        self.distill, self.visits, self.threshold = distill, visits, threshold
        self.label, self.rounds, self.repairs = label, rounds, repairs

    def teachers(self, item: Labelled) -> list[Teacher]:
        """Every condition learnt so far: the replay's, then ``item``'s."""
        stored = [
            Teacher.of(
                r.condition,
                r.offset,
                r.samples.x,
                None if r.p_cur is None else Labels(r.p_cur, r.p_pre, r.iterations),
            )
            for r in self.distill.stored()
        ]
        return [*stored, Teacher.of(len(stored), item.offset, item.data.x, item.labels)]

    def __call__(self, policy: GaussianPolicy, item: Labelled, seed: int) -> Checked:
        """Fit ``policy`` on ``item``, the replay and the states it visits; the kept policy is
        left in ``policy``."""
        teachers = self.teachers(item)
        losses = self.distill(policy, [item], seed)
        if not policy.trained:
            return Checked(losses, [float("nan")] * len(teachers), 0, None, 0)
        seen = self.visits(policy, teachers, seed, self.label)
        parts, rollouts, seconds = [seen.visited], seen.rollouts, seen.seconds
        best = Checked(losses, seen.distances, 0, None, 0)
        state = copy.deepcopy(policy.state_dict())
        refit = replace(self.distill.config, steps=max(1, self.distill.config.steps // 3))
        rounds = 0
        while rounds < self.rounds or (
            rounds < self.repairs and self.score(best.distances)[0] < len(teachers)
        ):
            rounds += 1
            policy.load_state_dict(state)
            missed = frozenset(i for i, d in enumerate(best.distances) if not d < self.threshold)
            visited = _joined(parts)
            round_seed = seed + 1_000_003 * rounds
            losses = self.distill(policy, [item], round_seed, missed, refit, visited)
            seen = self.visits(policy, teachers, round_seed, self.label)
            parts.append(seen.visited)
            rollouts += seen.rollouts
            seconds += seen.seconds
            if self.score(seen.distances) > self.score(best.distances):
                best, state = (
                    best._replace(losses=losses, distances=seen.distances),
                    copy.deepcopy(policy.state_dict()),
                )
        policy.load_state_dict(state)
        return best._replace(
            rounds=rounds, visited=_joined(parts), rollouts=rollouts, visit_seconds=seconds
        )

    def score(self, distances: list[float]) -> tuple[int, float]:
        """Positions reached, then minus the total distance: the larger the better."""
        return sum(d < self.threshold for d in distances), -sum(distances)


def _joined(parts: list[VisitedRows | None]) -> VisitedRows | None:
    """The rows of every part that has some (None: none has)."""
    present = [part for part in parts if part is not None]
    return VisitedRows.cat(present) if present else None
