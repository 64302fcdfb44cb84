"""Batch GPS as mirror-descent GPS (MDGPS; Montgomery & Levine, "Guided Policy Search via
Approximate Mirror Descent", 2016): every training condition at once, the reference with
nothing to forget.

    repeat:
        for every condition m: sample p_cur(m), fit dynamics, and take the C-step
            p_cur(m) <- argmin E[cost] s.t. KL(p_cur(m) || p_pre(m)) <= eps
            with p_pre(m) the global policy linearised around condition m's new samples
            (before the first S-step: against the previous p_cur, a trust region)
        pi <- S-step on every condition's samples of this iteration, labelled by the p_cur
              (and p_pre) just optimised there
    until every condition has ``success_phases`` iterations with successful samples, or a limit

It shares the stream's per-iteration step (:func:`~lolgps_torch.lolgps.local.iterate`), its
labelling and its S-step (:class:`~lolgps_torch.lolgps.distillation.Distiller`, with the same
network and augmentation). One checkpoint is written, at the end; then the replay, each
condition's successful samples labelled by its final controllers, as in the stream.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.checkpoint import save_policy
from lolgps_torch.data.records import ConditionSummary, DistillRecord
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.dynamics import GMMPrior, prior_from_config
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels, label
from lolgps_torch.lolgps.local import Linearizer, LocalLearner, iterate
from lolgps_torch.lolgps.probes import noiseless_distance, policy_distances
from lolgps_torch.lolgps.stream import Log, StreamConfig, Successes, condition_seed
from lolgps_torch.policy import GaussianPolicy, linearize_policy
from lolgps_torch.task import PegTask
from lolgps_torch.types import LinearGaussian


class BatchLearner:
    """All conditions learned together, with an S-step after every iteration.

    MDGPS samples p_cur itself and anchors the C-step to the policy, so ``alpha``,
    ``alpha_schedule`` and ``cstep_anchor`` are fixed by it
    (:func:`~lolgps_torch.lolgps.methods.method_config` records them); every other
    :class:`StreamConfig` field applies, and ``replay`` must stay on (every condition is in
    every S-step).
    """

    def __init__(self, task: PegTask, config: StreamConfig, folder: RunFolder, log: Log) -> None:
        if not config.replay:
            raise LolgpsError("batch GPS distils every condition at every S-step: keep the replay")
        self.task, self.config, self.folder, self.log = task, config, folder, log
        self.policy = GaussianPolicy(task.layout.dX, task.layout.dU, config.policy, task.device)
        self.replay = ReplayBuffer(folder.replay_path)
        self.distill = Distiller(task, config.policy, config.augment, config.augment_scale, None)

    def _linearizer(self, prior: GMMPrior) -> Linearizer | None:
        if not (self.config.use_pre and self.policy.trained):
            return None
        return lambda x: linearize_policy(self.policy, x, prior)

    def run(
        self,
        conditions: list[tuple[float, float]],
        on_condition: Callable[[ConditionSummary], None],
    ) -> list[ConditionSummary]:
        """Learn every condition together; returns the summary entries."""
        if self.replay.conditions():
            raise LolgpsError(f"{self.folder.path} holds a finished batch GPS run")
        cfg, task, limits = self.config, self.task, self.config.policy.limits()
        learners = [
            LocalLearner(
                task, offset, cfg.local, condition_seed(cfg, m), self.log, m, limits=limits
            )
            for m, offset in enumerate(conditions)
        ]
        priors = [prior_from_config(cfg.local.dynamics) for _ in conditions]
        pres: list[LinearGaussian | None] = [None] * len(conditions)
        found = [Successes() for _ in conditions]
        iterations, losses = 0, []
        for i in range(cfg.max_iterations):
            iterations = i + 1
            labelled = []
            for m, learner in enumerate(learners):
                p_cur = learner.p_cur
                samples, pres[m], record = iterate(
                    learner, p_cur, self._linearizer(priors[m]), True, (m, i, 0.0)
                )
                self.log(record)
                found[m].add(samples, Labels(p_cur, pres[m], i))
                labels = Labels(learner.p_cur, pres[m], iterations)
                labelled.append(Labelled(conditions[m], label(task, [samples], labels), labels))
            t0 = time.perf_counter()
            losses = self.distill(self.policy, labelled, cfg.seed * 1000 + i)
            rows = sum(int(item.data.x.shape[0]) for item in labelled) * task.T
            self.log(DistillRecord(len(conditions) - 1, time.perf_counter() - t0, rows, i))
            if all(len(f.kept) >= cfg.success_phases for f in found):
                break
        return self._finish(conditions, learners, found, pres, iterations, losses, on_condition)

    def _finish(
        self,
        conditions: list[tuple[float, float]],
        learners: list[LocalLearner],
        found: list[Successes],
        pres: list[LinearGaussian | None],
        iterations: int,
        losses: list[float],
        on_condition: Callable[[ConditionSummary], None],
    ) -> list[ConditionSummary]:
        """Summary entries, the final checkpoint and the replay of every condition."""
        threshold = self.task.config.world.success_threshold
        after = policy_distances(self.task, self.policy, conditions)
        summary, labelled = [], []
        for m, offset in enumerate(conditions):
            labels = Labels(learners[m].p_cur, pres[m], iterations)
            labelled.append(Labelled(offset, label(self.task, found[m].kept, labels), labels))
            local = noiseless_distance(self.task, learners[m].p_cur, offset, learners[m].limits)
            entry = ConditionSummary(
                condition=m,
                offset=list(offset),
                iterations=iterations,
                first_success_iteration=found[m].first,
                successful_samples=int(labelled[m].data.x.shape[0]),
                local_final_distance=local,
                local_success=local < threshold,
                labels_from_iteration=iterations,
                policy_final_distance_after=after[m],
                policy_success_after=after[m] < threshold,
                distill_loss=losses[-1] if losses else None,
                rollouts=iterations * learners[m].config.samples,
                policy_final_distance_end=after[m],
                policy_success_end=after[m] < threshold,
            )
            summary.append(entry)
            on_condition(entry)
        last = len(conditions) - 1
        save_policy(self.folder.checkpoint_dir(last), self.policy)
        self.folder.write_entry(last, summary[-1].to_json())
        for m, item in enumerate(labelled):
            labels = item.labels
            self.replay.append_condition(
                m, item.offset, item.data, iterations, labels.p_cur, labels.p_pre
            )
        return summary
