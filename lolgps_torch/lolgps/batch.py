"""Batch GPS, the reference with nothing to forget: every training condition at once.

    repeat:
        for every condition m: sample p_act(m), fit dynamics, p_pre(m) <- linearise pi around
            the samples (once pi is trained), C-step against p_bar (as the stream)
        pi <- S-step on the D_g of every condition, labelled by each one's p_cur and p_pre
    until every condition has ``success_phases`` iterations with successful samples, or a limit

It shares the stream's per-iteration step (:func:`~lolgps_torch.lolgps.local.iterate`), its
D_g labelling and its S-step (:class:`~lolgps_torch.lolgps.distillation.Distiller`). One
checkpoint is written, at the end; the replay is written last, as in the stream.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from lolgps_torch.controllers import mix
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.checkpoint import save_policy
from lolgps_torch.data.records import ConditionSummary, DistillRecord
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.dynamics import GMMPrior, prior_from_config
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.distillation import Distiller, Labelled, Labels, label
from lolgps_torch.lolgps.local import Linearizer, LocalLearner, iterate
from lolgps_torch.lolgps.stream import (
    Log,
    StreamConfig,
    Successes,
    condition_seed,
    noiseless_distance,
    policy_distances,
)
from lolgps_torch.policy import GaussianPolicy, linearize_policy
from lolgps_torch.task import PegTask
from lolgps_torch.types import LinearGaussian


class BatchLearner:
    """All conditions learned together, with an S-step after every iteration.

    Every :class:`StreamConfig` field applies except ``replay`` (every condition is in every
    S-step), which must stay on.
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
        cfg, task = self.config, self.task
        learners = [
            LocalLearner(task, offset, cfg.local, seed=condition_seed(cfg, m))
            for m, offset in enumerate(conditions)
        ]
        priors = [prior_from_config(cfg.local.dynamics) for _ in conditions]
        pres: list[LinearGaussian | None] = [None] * len(conditions)
        found = [Successes() for _ in conditions]
        alpha, iterations, losses = cfg.alpha, 0, []
        labelled: list[Labelled] = []
        for i in range(cfg.max_iterations):
            iterations = i + 1
            for m, learner in enumerate(learners):
                p_cur, p_pre = learner.p_cur, pres[m]
                p_act = p_cur if p_pre is None else mix(p_pre, p_cur, alpha)
                used = alpha if p_pre is not None else 0.0
                linearize = self._linearizer(priors[m])
                samples, new_pre, record = iterate(
                    learner, p_act, linearize, cfg.cstep_anchor == "pre", (m, i, used)
                )
                self.log(record)
                pres[m] = new_pre if new_pre is not None else p_pre
                found[m].add(samples, Labels(p_cur, pres[m], i))
            labelled = []
            for m, f in enumerate(found):
                labels = Labels(learners[m].p_cur, pres[m], iterations)
                labelled.append(Labelled(conditions[m], label(task, f.kept, labels), labels))
            t0 = time.perf_counter()
            losses = self.distill(self.policy, labelled, cfg.seed * 1000 + i)
            rows = sum(int(item.data.x.shape[0]) for item in labelled) * task.T
            self.log(DistillRecord(len(conditions) - 1, time.perf_counter() - t0, rows, i))
            alpha = cfg.next_alpha(alpha)
            if all(len(f.kept) >= cfg.success_phases for f in found):
                break
        return self._finish(conditions, learners, found, labelled, iterations, losses, on_condition)

    def _finish(
        self,
        conditions: list[tuple[float, float]],
        learners: list[LocalLearner],
        found: list[Successes],
        labelled: list[Labelled],
        iterations: int,
        losses: list[float],
        on_condition: Callable[[ConditionSummary], None],
    ) -> list[ConditionSummary]:
        """Summary entries, the final checkpoint and the replay of every condition."""
        threshold = self.task.config.world.success_threshold
        after = policy_distances(self.task, self.policy, conditions)
        summary = []
        for m, offset in enumerate(conditions):
            local = noiseless_distance(self.task, learners[m].p_cur, offset)
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
