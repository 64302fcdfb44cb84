"""LOLGPS over a stream of conditions (paper Algorithm 2, docs/ALGORITHM.md section 8).

    pi <- fresh net
    for each condition m as it arrives:
        p_cur <- hold controller, planned on the arm's model; p_pre <- none; D_g(m) <- {}
        phases <- transfer_phases if transfer is on, pi is trained and its noiseless rollout
                  at m succeeds, else success_phases
        repeat:
            p_act <- p_cur if no p_pre else alpha p_pre + (1 - alpha) p_cur       (eq. 6)
            D_i <- N rollouts of p_act; fit dynamics
            p_pre <- linearise pi around D_i, if pi was trained                  (line 14)
            p_cur <- argmin E[cost] s.t. KL(p_cur || p_bar) <= eps                (eq. 7)
                     (p_bar = p_pre with cstep_anchor "pre", else the previous p_cur)
            D_g(m) += successful rollouts of D_i
        until successful samples from ``phases`` iterations are in D_g(m), or a limit
        label D_g(m) with the final p_cur and p_pre (if its noiseless rollout misses: with
            the newest successfully sampled ones whose noiseless rollout succeeds)
        pi <- argmin KL(pi || p_cur) + lambda KL(pi || p_pre) over D_g(m) + replay D_g(<m) (eq. 8)
              + the states pi visits at every condition <= m, labelled by that condition's
              p_cur and p_pre where they are valid; refitted a few rounds, and while pi misses
              a condition <= m (a few times at most), from the best pi

Naive sequential learning is the same loop without p_pre and without the replay.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, NamedTuple, get_args

from lolgps_torch.controllers import mix
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.checkpoint import load_policy, save_policy
from lolgps_torch.data.records import (
    ConditionSummary,
    DistillRecord,
    IdentifiedRecord,
    IterationRecord,
)
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.dynamics import prior_from_config
from lolgps_torch.errors import LolgpsError, NumericalError, check_fields
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels, label
from lolgps_torch.lolgps.local import Linearizer, LocalConfig, LocalLearner, iterate
from lolgps_torch.lolgps.onpolicy import CheckedSStep, PolicyVisits, VisitsOn
from lolgps_torch.lolgps.plans import PlannedStarts
from lolgps_torch.lolgps.probes import noiseless_distance, policy_distances
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, linearize_policy
from lolgps_torch.task import ROLLOUT_KINDS, PegTask
from lolgps_torch.types import LinearGaussian, Trajectories

AlphaSchedule = Literal["constant", "dynamic"]
Transfer = Literal["none", "policy"]
CStepAnchor = Literal["previous", "pre"]
Log = Callable[[IterationRecord | IdentifiedRecord | DistillRecord], None]


@dataclass(frozen=True)
class StreamConfig:
    """Settings of the outer loop.

    :param alpha: weight of p_pre in p_act (the initial value when dynamic), in [0, 1].
    :param alpha_schedule: constant, or dynamic (alpha += alpha_step per iteration).
    :param alpha_step: the dynamic schedule's increment (paper: 0.005).
    :param use_pre: linearise the global policy into p_pre (off: naive sequential).
    :param cstep_anchor: the C-step's p_bar once p_pre exists: pre (paper eq. 7,
        KL(p_cur || p_pre) <= eps) or previous (the previous p_cur, a trust region).
    :param replay: distil on the replay of earlier conditions too (off: an ablation).
    :param success_phases: iterations with successful samples needed in D_g (paper: 9).
    :param augment: perturbed copies of each D_g state in the S-step.
    :param augment_scale: perturbation size, in per-step standard deviations of D_g's states.
    :param max_iterations: iteration limit per condition.
    :param transfer: forward transfer: none (the paper: ``success_phases`` at every
        condition), or policy: where the trained policy's noiseless rollout at a new
        condition already succeeds (one probe rollout), local learning stops after
        ``transfer_phases`` iterations with successes; D_g is labelled by its local
        controllers all the same.
    :param transfer_phases: the iterations with successes needed where the policy transfers.
        2 rather than 3 cost 7 % fewer rollouts over 26 streams on 11 arms and 30 % fewer on
        the 24-condition square stream, with the same positions and test areas (4 mm
        robustness: 13 misses of 1 664 against 7); 1 lost test areas (docs/HISTORY.md
        [R24] [H12]).
    :param repairs: the most S-step rounds while the policy's noiseless rollouts miss a
        condition learnt so far (0 with ``onpolicy_rounds`` 0: one S-step, as in the paper).
    :param onpolicy: label the states the policy visits at every condition learnt so far
        after each S-step where they lie inside the teachers' support; they join the data of
        the S-step's later rounds and of every later S-step.
    :param onpolicy_rounds: S-step rounds always run after the first fit, each followed by a
        visit (0: none).
    :param onpolicy_noisy: rollouts with the policy's own noise per condition and visit,
        besides the noiseless one.
    :param onpolicy_gate: the teachers' support, in standard deviations of D_g's states.
    :param onpolicy_floor: the smallest standard deviation of a joint angle in the support
        (rad; the joint velocities': 10 times as much, rad/s).
    :param visits: where the S-step's visits and closed-loop checks roll the policy out: on
        the arm, or on the arm's model (a simulated world of its description as the learner
        believes it: PegTask.simulate), which spares a real arm every visit; the policy's
        checks before and after each condition stay on the arm.
    :param seed: seeds every condition's sampling and every S-step.
    """

    alpha: float = 0.0
    alpha_schedule: AlphaSchedule = "dynamic"
    alpha_step: float = 0.005
    use_pre: bool = True
    cstep_anchor: CStepAnchor = "previous"
    replay: bool = True
    success_phases: int = 9
    augment: int = 4
    augment_scale: float = 2.0
    max_iterations: int = 25
    transfer: Transfer = "policy"
    transfer_phases: int = 2
    repairs: int = 6
    onpolicy: bool = True
    onpolicy_rounds: int = 2
    onpolicy_noisy: int = 2
    onpolicy_gate: float = 3.0
    onpolicy_floor: float = 0.005
    visits: VisitsOn = "arm"
    seed: int = 0
    local: LocalConfig = field(default_factory=LocalConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)

    def __post_init__(self) -> None:
        options = (
            ("alpha_schedule", AlphaSchedule),
            ("cstep_anchor", CStepAnchor),
            ("transfer", Transfer),
            ("visits", VisitsOn),
        )
        for name, kind in options:
            if getattr(self, name) not in get_args(kind):
                raise LolgpsError(f"{name} {getattr(self, name)!r}: one of {get_args(kind)}")
        check_fields(
            self,
            {
                "alpha": 0.0 <= self.alpha <= 1.0,
                "alpha_step": 0.0 <= self.alpha_step <= 1.0,
                "success_phases": self.success_phases >= 1,
                "augment": self.augment >= 0,
                "augment_scale": 0.0 <= self.augment_scale < float("inf"),
                "max_iterations": self.max_iterations >= 1,
                "repairs": self.repairs >= 0,
                "onpolicy_rounds": self.onpolicy_rounds >= 0,
                "onpolicy_noisy": self.onpolicy_noisy >= 0,
                "onpolicy_gate": 0.0 < self.onpolicy_gate < float("inf"),
                "onpolicy_floor": 0.0 < self.onpolicy_floor < float("inf"),
                "transfer_phases": self.transfer_phases >= 1,
                "seed": self.seed >= 0,
            },
        )

    def next_alpha(self, alpha: float) -> float:
        """The weight of p_pre at the next iteration."""
        return min(1.0, alpha + self.alpha_step) if self.alpha_schedule == "dynamic" else alpha


class Outcome(NamedTuple):
    """What local learning at one condition produced: its successes, the final controllers
    with the iteration count, the rollouts drawn, a numerical failure that ended it early
    (None: none), and the rollouts the arm's controller stopped at a limit."""

    found: Successes
    final: Labels
    rollouts: int
    failure: str | None
    faults: int


class Successes:
    """A condition's successful rollouts so far, and the controllers of every iteration that
    drew some (``tried``, oldest first)."""

    def __init__(self) -> None:
        self.kept: list[Trajectories] = []
        self.first: int | None = None
        self.tried: list[Labels] = []

    def add(self, samples: Trajectories, labels: Labels) -> None:
        """Keep the successful ones of ``samples``, drawn by ``labels.p_cur``'s p_act."""
        if samples.success.any():
            self.first = labels.iteration if self.first is None else self.first
            self.kept.append(Trajectories(*(f[samples.success] for f in samples)))
            self.tried.append(labels)


class StreamLearner:
    """Runs the stream, condition by condition, into a run folder it can resume from."""

    def __init__(self, task: PegTask, config: StreamConfig, folder: RunFolder, log: Log) -> None:
        self.task, self.config, self.folder, self.log = task, config, folder, log
        self.policy = GaussianPolicy(task.layout.dX, task.layout.dU, config.policy, task.device)
        self.replay = ReplayBuffer(folder.replay_path)
        distill = Distiller(
            task,
            config.policy,
            config.augment,
            config.augment_scale,
            self.replay if config.replay else None,
        )
        self.sstep = checked_sstep(task, config, distill)
        self.starts = PlannedStarts(task, config.local)  # each first p_cur, planned on the model

    def learn_condition(
        self, index: int, offset: tuple[float, float], upcoming: tuple[float, float] | None = None
    ) -> ConditionSummary:
        """One condition of Algorithm 2: local learning, D_g and the S-step with replay;
        returns its summary entry. The first controller at the ``upcoming`` condition's offset
        is planned during the S-step where a rollout worker is idle (:class:`PlannedStarts`)."""
        cfg, seed = self.config, condition_seed(self.config, index)
        counted, stopped = Counter(self.task.arm_rollouts), Counter(self.task.arm_faults)
        seconds_before = self.task.arm_seconds()
        simulated, simulated_faults = self.task.model_rollouts, self.task.model_faults
        learner = LocalLearner(
            self.task, offset, cfg.local, seed, self.log, index, self.starts.plan,
            cfg.policy.limits(),
        )  # fmt: skip
        linearize = self.linearizer()  # None while pi is untrained, and in naive learning
        phases, probes = self.phases(offset)
        outcome = self.learn_locally(learner, linearize, index, phases, probes)
        failure, final = outcome.failure, outcome.final
        labels, local = self.teacher(outcome, offset)  # D_g is labelled here
        data = label(self.task, outcome.found.kept, labels)
        self.starts.request(upcoming)  # planned during the S-step, where a worker is idle
        t0 = time.perf_counter()
        checked = self.sstep(self.policy, Labelled(offset, data, labels), seed)
        losses, after, repairs = checked.losses, checked.distances[-1], checked.rounds
        rows = int(data.x.shape[0]) * self.task.T
        seconds = time.perf_counter() - t0
        self.log(
            DistillRecord(index, seconds, rows, repairs=repairs, time_visits=checked.visit_seconds)
        )
        entry = ConditionSummary(
            condition=index,
            offset=list(offset),
            iterations=final.iteration,
            first_success_iteration=outcome.found.first,
            successful_samples=int(data.x.shape[0]),
            local_final_distance=local,
            local_success=local < self.threshold,
            labels_from_iteration=labels.iteration,
            policy_final_distance_after=after,
            policy_success_after=after < self.threshold,
            distill_loss=losses[-1] if losses else None,
            failure=failure,
            rollouts=outcome.rollouts,
            repairs=repairs,
            policy_rollouts=checked.rollouts,
            visited_rows=0 if checked.visited is None else checked.visited.R,
            faults=outcome.faults,
            arm_rollouts={k: self.task.arm_rollouts[k] - counted[k] for k in ROLLOUT_KINDS},
            arm_faults={k: self.task.arm_faults[k] - stopped[k] for k in ROLLOUT_KINDS},
            arm_seconds=arm_seconds(self.task, seconds_before),
            model_rollouts=self.task.model_rollouts - simulated,
            model_faults=self.task.model_faults - simulated_faults,
        )
        # Checkpoint first, replay last: a condition is complete once its replay group exists.
        save_policy(self.folder.checkpoint_dir(index), self.policy)
        self.folder.write_entry(index, entry.to_json())
        self.replay.append_condition(
            index, offset, data, final.iteration, labels.p_cur, labels.p_pre, checked.visited
        )
        return entry

    def teacher(self, outcome: Outcome, offset: tuple[float, float]) -> tuple[Labels, float]:
        """The controllers that label D_g, and their p_cur's noiseless final distance (the
        condition's local controller): the newest of the final p_cur (which no sample has
        tried; not after a numerical failure) and the p_cur of each iteration with successful
        samples whose noiseless rollout succeeds, else the closest of them, so that the policy
        never imitates a controller known to miss when a better one was tried."""
        candidates = [] if outcome.failure else [outcome.final]
        scored = []
        for labels in candidates + outcome.found.tried[::-1]:
            local = self.noiseless(labels.p_cur, offset)
            if local < self.threshold:
                return labels, local
            scored.append((local, labels))
        if not scored:  # a numerical failure before any success
            return outcome.final, float("inf")
        local, labels = min(scored, key=lambda pair: pair[0])
        return labels, local

    def noiseless(self, p: LinearGaussian, offset: tuple[float, float]) -> float:
        """Final distance (m) of the controller ``p``'s noiseless rollout at ``offset``."""
        return noiseless_distance(self.task, p, offset, self.config.policy.limits())

    def phases(self, offset: tuple[float, float]) -> tuple[int, int]:
        """The iterations with successes local learning needs at ``offset``, and the probe
        rollouts spent to decide: ``transfer_phases`` (at most ``success_phases``) where
        transfer is on and the trained policy's noiseless rollout already succeeds there
        (forward transfer: fewer rollouts where the policy does the task), else
        ``success_phases``."""
        cfg = self.config
        if cfg.transfer == "none" or not self.policy.trained:
            return cfg.success_phases, 0
        reached = policy_distances(self.task, self.policy, [offset])[0] < self.threshold
        if not reached:
            return cfg.success_phases, 1
        return min(cfg.transfer_phases, cfg.success_phases), 1

    def learn_locally(
        self,
        learner: LocalLearner,
        linearize: Linearizer | None,
        index: int,
        phases: int,
        probes: int = 0,
    ) -> Outcome:
        """Algorithm 2's inner loop: iterations of sample, fit, p_pre and C-step until
        ``phases`` iterations had successful samples, or the limit. A numerical failure ends
        the loop and is reported; the stream goes on. The rollouts counted include ``probes``
        already spent at the condition."""
        cfg = self.config
        p_pre: LinearGaussian | None = None
        alpha, found, iterations, failure, faults = cfg.alpha, Successes(), 0, None, 0
        try:
            for i in range(cfg.max_iterations):
                iterations, p_cur = i + 1, learner.p_cur
                p_act = p_cur if p_pre is None else mix(p_pre, p_cur, alpha)  # eq. 6
                used = alpha if p_pre is not None else 0.0
                samples, p_pre, record = iterate(  # fit, p_pre, C-step (eq. 7)
                    learner, p_act, linearize, cfg.cstep_anchor == "pre", (index, i, used)
                )
                self.log(record)
                faults += record.faults
                found.add(samples, Labels(p_cur, p_pre, i))
                alpha = cfg.next_alpha(alpha)
                if len(found.kept) >= phases:
                    break
        except NumericalError as error:
            failure = f"iteration {iterations - 1}: {error}"
        rollouts = probes + iterations * cfg.local.samples
        final = Labels(learner.p_cur, p_pre, iterations)
        return Outcome(found, final, rollouts, failure, faults)

    def linearizer(self) -> Linearizer | None:
        """p_pre's fit around a batch of samples (GMM-prior regression on the policy's own
        actions, docs/ALGORITHM.md section 6), or None without a trained policy."""
        if not (self.config.use_pre and self.policy.trained):
            return None
        prior = prior_from_config(self.config.local.dynamics)
        return lambda x: linearize_policy(self.policy, x, prior)

    @property
    def threshold(self) -> float:
        return self.task.config.world.success_threshold

    def run(
        self,
        conditions: list[tuple[float, float]],
        on_condition: Callable[[ConditionSummary], None],
    ) -> list[ConditionSummary]:
        """Learn every condition not yet completed in the folder, checkpointing after each;
        then test the final policy at every one of them."""
        summary = self._restore()
        for index in range(len(summary), len(conditions)):
            upcoming = conditions[index + 1] if index + 1 < len(conditions) else None
            entry = self.learn_condition(index, conditions[index], upcoming)
            summary.append(entry)
            on_condition(entry)
        return self.finish(summary, conditions)

    def finish(
        self, summary: list[ConditionSummary], conditions: list[tuple[float, float]]
    ) -> list[ConditionSummary]:
        """Set every entry's ``policy_final_distance_end`` from the final policy."""
        for entry, dist in zip(
            summary, policy_distances(self.task, self.policy, conditions), strict=True
        ):
            entry.policy_final_distance_end = dist
            entry.policy_success_end = dist < self.threshold
        return summary

    def _restore(self) -> list[ConditionSummary]:
        """Resume after the last condition whose replay group was written (the replay is
        written last, so its policy checkpoint and summary entry exist)."""
        done = len(self.replay.conditions())
        if done > 0:
            self.policy = load_policy(self.folder.checkpoint_dir(done - 1), self.task.device)
        return [ConditionSummary.from_json(self.folder.read_entry(i)) for i in range(done)]


def checked_sstep(task: PegTask, config: StreamConfig, distill: Distiller) -> CheckedSStep:
    """The S-step ``distill``, on the policy's own states and checked in closed loop, with
    the stream's settings."""
    visits = PolicyVisits(
        task, config.onpolicy_noisy, config.onpolicy_gate, config.onpolicy_floor, config.visits
    )
    threshold = task.config.world.success_threshold
    return CheckedSStep(
        distill, visits, threshold, config.onpolicy, config.onpolicy_rounds, config.repairs
    )


def arm_seconds(task: PegTask, before: float | None) -> float | None:
    """A real arm's seconds since it had ``before`` (None in a simulator)."""
    now = task.arm_seconds()
    return None if now is None or before is None else now - before


def condition_seed(config: StreamConfig, index: int) -> int:
    """The seed of condition ``index``'s sampling and S-step."""
    return config.seed * 1000 + index
