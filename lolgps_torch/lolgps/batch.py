"""Batch GPS (mirror-descent style), the upper reference: every training condition at once.

    repeat:
        for every condition m: sample p_act(m), fit dynamics, p_pre(m) <- linearise pi around
            the samples (once pi is trained), C-step against p_bar (as the stream)
        pi <- S-step on the D_g of all conditions so far, labelled by each one's p_cur and p_pre
    until every condition has ``success_phases`` iterations with successful samples, or a limit

The policy sees all conditions in every S-step, so there is nothing to forget; it is the
reference LOLGPS is measured against.  One checkpoint is written at the end.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from lolgps_torch.controllers import mix
from lolgps_torch.dynamics import prior_from_config
from lolgps_torch.lolgps.local import LocalLearner
from lolgps_torch.lolgps.stream import Labelled, StreamLearner, _write_json
from lolgps_torch.types import LinearGaussian, Trajectories


class BatchLearner(StreamLearner):
    """All conditions learned together, with an S-step after every iteration."""

    def run(
        self, conditions: list[tuple[float, float]], on_condition: Callable[[dict[str, Any]], None]
    ) -> list[dict[str, Any]]:
        cfg, task = self.config, self.task
        learners = [
            LocalLearner(task, offset, cfg.local, seed=cfg.seed * 1000 + m)
            for m, offset in enumerate(conditions)
        ]
        priors = [prior_from_config(cfg.local.dynamics) for _ in conditions]
        pres: list[LinearGaussian | None] = [None] * len(conditions)
        kept: list[list[Trajectories]] = [[] for _ in conditions]
        first: list[int | None] = [None] * len(conditions)
        iterations = 0
        for i in range(cfg.max_iterations):
            iterations = i + 1
            for m, learner in enumerate(learners):
                p_pre = pres[m]
                p_act = learner.p_cur if p_pre is None else mix(p_pre, learner.p_cur, cfg.alpha)
                t0 = time.perf_counter()
                samples = learner.sample(p_act)
                t1 = time.perf_counter()
                fit = learner.fit(p_act, samples)
                if cfg.use_pre and self.policy_trained:
                    pres[m] = p_pre = self._linearize(samples.x, priors[m])
                t2 = time.perf_counter()
                anchor = p_pre if p_pre is not None and cfg.cstep_anchor == "pre" else learner.p_cur
                epsilon, eta, kl = learner.improve(fit, anchor)
                t3 = time.perf_counter()
                if samples.success.any():
                    first[m] = i if first[m] is None else first[m]
                    kept[m].append(Trajectories(*(f[samples.success] for f in samples)))
                self.log(self._iteration_record(m, i, samples, epsilon, eta, kl, (t0, t1, t2, t3)))
            labelled: list[Labelled] = [
                (
                    conditions[m],
                    self._with_targets(kept[m], learners[m].p_cur, pres[m]),
                    learners[m].p_cur,
                    pres[m],
                )
                for m in range(len(conditions))
            ]
            t0 = time.perf_counter()
            self._distill(labelled, cfg.seed * 1000 + i)
            self.log(
                {
                    "iteration": i,
                    "event": "distilled",
                    "time_distill": time.perf_counter() - t0,
                    "condition": len(conditions) - 1,
                }
            )
            if all(len(k) >= cfg.success_phases for k in kept):
                break

        last = len(conditions) - 1
        after = self._policy_distances(list(conditions))
        threshold = task.config.world.success_threshold
        self.summary = []
        for m, offset in enumerate(conditions):
            local = self._rollout_noiseless(learners[m].p_cur, offset)
            entry = {
                "condition": m,
                "offset": list(offset),
                "iterations": iterations,
                "first_success_iteration": first[m],
                "successful_samples": sum(k.x.shape[0] for k in kept[m]),
                "local_final_distance": local,
                "local_success": local < threshold,
                "policy_final_distance_after": after[m],
                "policy_success_after": after[m] < threshold,
                "policy_final_distance_end": after[m],
                "policy_success_end": after[m] < threshold,
            }
            self.summary.append(entry)
            on_condition(entry)
        folder = self._checkpoint_dir(last)
        self.policy.save(folder)
        _write_json(f"{folder}/entry.json", self.summary[-1])
        for m, offset in enumerate(conditions):
            _, data, p_cur, p_pre = labelled[m]
            self.replay.append_condition(m, offset, data, iterations, p_cur, p_pre)
        return self.summary
