"""LOLGPS over a stream of conditions (paper Algorithm 2, ALGORITHM.md section 8).

    pi <- fresh net; p_pre <- none
    for each condition m as it arrives:
        p_cur <- initial controller; D_g(m) <- {}
        repeat:
            p_act <- p_cur if no p_pre else alpha p_pre + (1 - alpha) p_cur       (eq. 6)
            D_i <- N rollouts of p_act; fit dynamics
            p_pre <- linearise pi around D_i, if pi was trained                  (line 14)
            p_cur <- argmin E[cost] s.t. KL(p_cur || p_bar) <= eps                (eq. 7)
                     (p_bar = p_pre with cstep_anchor "pre", else the previous p_cur)
            D_g(m) += successful rollouts of D_i, with the p_cur and p_pre targets
        until successful samples from ``success_phases`` iterations are in D_g(m), or a limit
        pi <- argmin KL(pi || p_cur) + KL(pi || p_pre) over D_g(m) + replay of D_g(<m)  (eq. 8)

The baselines share this loop: naive sequential drops p_pre and the replay.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from lolgps_torch.controllers import mix
from lolgps_torch.data import ReplayBuffer
from lolgps_torch.dynamics import GMMPrior, prior_from_config
from lolgps_torch.lolgps.corrections import CorrectionConfig, Teacher, teacher_reference, visit
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner
from lolgps_torch.policy import (
    GaussianPolicy,
    PolicyConfig,
    distill,
    linearize_policy,
    linearize_policy_jacobian,
    policy_actor,
)
from lolgps_torch.sim.rollout import linear_gaussian_actor
from lolgps_torch.task import PegTask
from lolgps_torch.types import ConditionSamples, DistillBatch, LinearGaussian, Trajectories


@dataclass(frozen=True)
class StreamConfig:
    """Settings of the outer loop.

    :param alpha: weight of p_pre in p_act (the initial value when dynamic).
    :param alpha_schedule: ``constant``, or ``dynamic`` (alpha += alpha_step per iteration).
    :param alpha_step: the dynamic schedule's increment (paper: 0.005).
    :param use_pre: linearise the global policy into p_pre (off: naive sequential).
    :param pre_fit: how p_pre is fitted: ``gmm`` (regression on the policy's actions at the
        samples with a GMM prior, ALGORITHM.md section 6) or ``jacobian`` (the policy's own
        derivative at the samples, see :func:`lolgps_torch.policy.linearize_policy_jacobian`).
    :param plan_through_mixture: the C-step optimises p_act (p_cur's share of the mixture,
        :mod:`lolgps_torch.trajopt.mixture`) instead of p_cur as if it acted alone.
    :param cstep_anchor: the C-step's p_bar once p_pre exists: ``pre`` (paper eq. 7,
        KL(p_cur || p_pre) <= eps) or ``previous`` (the previous p_cur, a trust region).
    :param replay: distil on the replay of earlier conditions too (off: an ablation).
    :param success_phases: iterations with successful samples needed in D_g (paper: 9).
    :param augment: perturbed copies of each D_g state added to the current condition's S-step,
        labelled by the same linear-Gaussian controllers (valid at any state), so the policy
        learns their feedback, not only their actions along the successful trajectories.
    :param augment_scale: perturbation size, in per-step standard deviations of D_g's states.
    :param augment_mode: ``independent`` perturbs every state dimension on its own;
        ``kinematic`` perturbs q and q-dot only and recomputes the points, p(q) - p*, and their
        velocities, J(q) q-dot, so that each copy is a state the arm can be in.
    :param max_iterations: iteration limit per condition.
    :param consolidate: MDGPS iterations after the condition's S-step: sample p_cur, C-step
        against the policy now trained on this condition (``KL(p_cur || p_pre) <= eps``), add
        the successes to D_g and distil again, so the local controller moves towards what the
        policy can represent.
    :param consolidate_steps: Adam steps of each consolidation S-step.
    :param corrections: policy-correction rounds after each S-step's first fit.
    :param refits: checked refits of the condition's S-step. The policy runs noiselessly at
        every condition it has learnt (the earlier ones only with the replay); while it misses
        one, it is refitted from the best weights so far (``refit_steps`` Adam steps, a fresh
        minibatch draw) and the refit is kept only if it succeeds at more of them (ties: a
        lower mean final distance). Consolidation iterations pass the same check, and the first
        that does not improve is undone and ends the consolidation.
    :param refit_steps: Adam steps of each refit.
    :param seed: seeds every condition's sampling and every S-step.
    """

    alpha: float = 0.0
    alpha_schedule: str = "dynamic"
    alpha_step: float = 0.005
    use_pre: bool = True
    pre_fit: str = "gmm"
    plan_through_mixture: bool = False
    cstep_anchor: str = "previous"
    replay: bool = True
    success_phases: int = 9
    augment: int = 4
    augment_scale: float = 2.0
    augment_mode: str = "kinematic"
    max_iterations: int = 25
    consolidate: int = 0
    consolidate_steps: int = 1000
    refits: int = 0
    refit_steps: int = 1000
    seed: int = 0
    local: LocalConfig = field(default_factory=LocalConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    corrections: CorrectionConfig = field(default_factory=CorrectionConfig)


# a condition's hole offset and D_g with the controllers that label it (p_cur, p_pre)
Labelled = tuple[tuple[float, float], ConditionSamples, LinearGaussian, LinearGaussian | None]
Labels = tuple[LinearGaussian, LinearGaussian | None, int]


def controller_targets(p: LinearGaussian, x: Tensor) -> tuple[Tensor, Tensor]:
    """Means ``[M, T, dU]`` and precisions ``[M, T, dU, dU]`` of ``p`` at states ``[M, T, dX]``."""
    mean = p.mean_action(x)
    prec = p.precision().expand(x.shape[0], *p.cov.shape)
    return mean, prec


class StreamLearner:
    """Runs the stream, condition by condition, into an output folder it can resume from."""

    def __init__(
        self,
        task: PegTask,
        config: StreamConfig,
        out: str,
        log: Callable[[dict[str, Any]], None],
    ) -> None:
        self.task, self.config, self.out, self.log = task, config, out, log
        lay = task.layout
        self.policy = GaussianPolicy(lay.dX, lay.dU, config.policy, task.device)
        self.replay = ReplayBuffer(os.path.join(out, "replay.h5"))
        self.summary: list[dict[str, Any]] = []

    # -- one condition -------------------------------------------------------------------
    def learn_condition(self, index: int, offset: tuple[float, float]) -> dict[str, Any]:
        """Algorithm 2's inner loop at one condition; returns its summary entry."""
        cfg, task = self.config, self.task
        learner = LocalLearner(task, offset, cfg.local, seed=cfg.seed * 1000 + index)
        pre_prior = (
            prior_from_config(cfg.local.dynamics) if cfg.use_pre and self.policy_trained else None
        )
        p_pre: LinearGaussian | None = None
        alpha = cfg.alpha
        kept: list[Trajectories] = []
        first_success: int | None = None
        # the p_cur (and p_pre) of the latest iteration whose samples succeeded
        sampled: Labels | None = None
        iterations = 0
        for i in range(cfg.max_iterations):
            iterations = i + 1
            p_cur = learner.p_cur
            p_act = p_cur if p_pre is None else mix(p_pre, p_cur, alpha)
            samples, p_pre = self._step(
                index, i, learner, p_act, pre_prior, cfg.cstep_anchor == "pre", alpha
            )
            if samples.success.any():
                first_success = i if first_success is None else first_success
                kept.append(Trajectories(*(f[samples.success] for f in samples)))
                sampled = (p_cur, p_pre, i)
            if cfg.alpha_schedule == "dynamic":
                alpha = min(1.0, alpha + cfg.alpha_step)
            if len(kept) >= cfg.success_phases:
                break

        threshold = task.config.world.success_threshold
        local = self._rollout_noiseless(learner.p_cur, offset)
        final = (learner.p_cur, p_pre, iterations)
        label_cur, label_pre, labels_from = label_source(final, local < threshold, sampled)
        t0 = time.perf_counter()
        data = self._with_targets(kept, label_cur, label_pre)
        seed = cfg.seed * 1000 + index
        current: list[Labelled] = [(offset, data, label_cur, label_pre)]
        losses = self._distill(current, seed)
        check = [offset] + (self.replay.offsets() if cfg.replay else [])
        best = None
        if cfg.refits > 0:
            best, refit_losses = self._refit(index, current, check, seed)
            losses = refit_losses if refit_losses is not None else losses
        t_distill = time.perf_counter() - t0
        if cfg.use_pre and cfg.consolidate > 0:
            prior = pre_prior if pre_prior is not None else prior_from_config(cfg.local.dynamics)
            for j in range(cfg.consolidate):
                before = (data, p_pre, learner.p_cur, losses, self._snapshot())
                before_labels = (label_cur, label_pre, labels_from)
                samples, p_pre = self._step(index, iterations, learner, learner.p_cur, prior, True)
                if samples.success.any():
                    kept.append(Trajectories(*(f[samples.success] for f in samples)))
                iterations += 1
                label_cur, label_pre, labels_from = learner.p_cur, p_pre, iterations
                data = self._with_targets(kept, label_cur, label_pre)
                seed = (cfg.seed * 1000 + index) * 100 + j + 1
                losses = self._distill(
                    [(offset, data, learner.p_cur, p_pre)], seed, cfg.consolidate_steps
                )
                if best is None:
                    continue
                score = self._score(check)
                if score <= best:
                    data, p_pre, learner.p_cur, losses, state = before
                    label_cur, label_pre, labels_from = before_labels
                    self.policy.load_state_dict(state)
                    self.log({"condition": index, "event": "consolidation undone", "round": j})
                    break
                best = score
            local = self._rollout_noiseless(learner.p_cur, offset)
        policy = self._policy_distances([offset])[0]
        entry = {
            "condition": index,
            "offset": list(offset),
            "iterations": iterations,
            "first_success_iteration": first_success,
            "successful_samples": int(data.x.shape[0]),
            "local_final_distance": local,
            "local_success": local < threshold,
            "labels_from_iteration": labels_from,
            "policy_final_distance_after": policy,
            "policy_success_after": policy < threshold,
            "distill_loss": losses[-1] if losses else None,
        }
        self.log(
            {
                "condition": index,
                "event": "distilled",
                "time_distill": t_distill,
                "distill_rows": int(data.x.shape[0]) * task.T,
            }
        )
        # Checkpoint first, replay last: a condition is complete once its replay group exists.
        folder = self._checkpoint_dir(index)
        self.policy.save(folder)
        _write_json(os.path.join(folder, "entry.json"), entry)
        self.replay.append_condition(index, offset, data, iterations, label_cur, label_pre)
        return entry

    def _step(
        self,
        index: int,
        iteration: int,
        learner: LocalLearner,
        p_act: LinearGaussian,
        prior: GMMPrior | None,
        anchor_to_pre: bool,
        alpha: float = 0.0,
    ) -> tuple[Trajectories, LinearGaussian | None]:
        """One iteration at condition ``index``: sample ``p_act`` (which mixes in p_pre with
        weight ``alpha``), fit the dynamics, linearise the policy into the new p_pre (when a
        ``prior`` is given, i.e. the policy is trained) and take the C-step against it
        (``anchor_to_pre``) or against the previous p_cur; logs the iteration's record.
        Returns the samples and the new p_pre."""
        t0 = time.perf_counter()
        samples = learner.sample(p_act)
        t1 = time.perf_counter()
        fit = learner.fit(p_act, samples)
        p_pre = self._linearize(samples.x, prior) if prior is not None else None
        t2 = time.perf_counter()
        anchor = p_pre if p_pre is not None and anchor_to_pre else learner.p_cur
        mixture = (
            (p_pre, alpha)
            if p_pre is not None and 0.0 < alpha < 1.0 and self.config.plan_through_mixture
            else None
        )
        epsilon, eta, kl = learner.improve(fit, anchor, mixture)
        t3 = time.perf_counter()
        mixed = alpha if p_pre is not None else 0.0
        times = (t0, t1, t2, t3)
        self.log(self._iteration_record(index, iteration, samples, epsilon, eta, kl, times, mixed))
        return samples, p_pre

    @staticmethod
    def _iteration_record(
        condition: int,
        iteration: int,
        samples: Trajectories,
        epsilon: float,
        eta: float,
        kl: float,
        times: tuple[float, float, float, float],
        alpha: float = 0.0,
    ) -> dict[str, Any]:
        """One metrics.jsonl line; ``times`` are the perf_counter stamps before sampling, after
        sampling, after fitting and after the C-step."""
        t0, t1, t2, t3 = times
        return {
            "condition": condition,
            "iteration": iteration,
            "alpha": alpha,
            "mean_cost": float(samples.cost.sum(1).mean()),
            "mean_distance": float(samples.final_distance.mean()),
            "best_distance": float(samples.final_distance.min()),
            "success_rate": float(samples.success.double().mean()),
            "epsilon": epsilon,
            "eta": eta,
            "kl": kl,
            "time_sample": t1 - t0,
            "time_fit": t2 - t1,
            "time_cstep": t3 - t2,
        }

    def _linearize(self, x: Tensor, prior: GMMPrior) -> LinearGaussian:
        """p_pre around the states ``x: [N, T, dX]`` by the configured ``pre_fit``."""
        if self.config.pre_fit == "jacobian":
            return linearize_policy_jacobian(self.policy, x)
        return linearize_policy(self.policy, x, prior)

    @property
    def policy_trained(self) -> bool:
        return bool(self.policy.trained)

    def _with_targets(
        self, kept: list[Trajectories], p_cur: LinearGaussian, p_pre: LinearGaussian | None
    ) -> ConditionSamples:
        """D_g: the successful rollouts with the final p_cur's and p_pre's action means and
        precisions at their states (one coherent feedback law per condition; M may be 0)."""
        lay, T, dev = self.task.layout, self.task.T, self.task.device
        if kept:
            x, u, cost, final, _ = (torch.cat(f) for f in zip(*kept, strict=True))
        else:
            x = torch.zeros(0, T, lay.dX, dtype=torch.float64, device=dev)
            u = torch.zeros(0, T, lay.dU, dtype=torch.float64, device=dev)
            cost, final = x.new_zeros(0, T), x.new_zeros(0)
        mean_cur, prec_cur, mean_pre, prec_pre, has_pre = _targets(x, p_cur, p_pre)
        return ConditionSamples(x, u, cost, final, mean_cur, prec_cur, mean_pre, prec_pre, has_pre)

    def _distill(self, current: list[Labelled], seed: int, steps: int | None = None) -> list[float]:
        """S-step on the given conditions' D_g, each with ``augment`` perturbed copies of its
        states labelled by the same linear-Gaussian controllers, plus the earlier conditions'
        D_g from the replay when it is on; then ``corrections.rounds`` rounds of policy
        corrections (:mod:`lolgps_torch.lolgps.corrections`) at all those conditions."""
        cfg, gen = self.config, torch.Generator().manual_seed(seed)
        batches, teachers = [], []
        for offset, data, p_cur, p_pre in current:
            batches.append(data.to_batch())
            if data.x.shape[0] == 0:
                continue
            teachers.append(Teacher(offset, p_cur, p_pre, teacher_reference(self.task, data.x)))
            if data.x.shape[0] > 1 and cfg.augment > 0:
                batches.append(self._augmented(data, p_cur, p_pre, gen, offset))
        earlier = self.replay.conditions() if cfg.replay else []
        for record in (self.replay.read_condition(i, self.task.device) for i in earlier):
            batches.append(record.samples.to_batch())
            if record.p_cur is not None and record.samples.x.shape[0] > 0:
                reference = teacher_reference(self.task, record.samples.x)
                teachers.append(Teacher(record.offset, record.p_cur, record.p_pre, reference))
        batch = _concat(batches)
        if batch.x.shape[0] == 0:
            return []
        first = cfg.policy if steps is None else replace(cfg.policy, steps=steps)
        losses = distill(self.policy, batch, first, gen)
        refit = replace(cfg.policy, steps=cfg.corrections.steps)
        for _ in range(cfg.corrections.rounds if teachers else 0):
            batch = _concat([batch, visit(self.task, self.policy, teachers, cfg.corrections, gen)])
            losses += distill(self.policy, batch, refit, gen)
        return losses

    def _score(self, offsets: list[tuple[float, float]]) -> tuple[int, float]:
        """The policy's noiseless rollouts at ``offsets``: (successes, minus the mean final
        distance), so that larger is better."""
        final = torch.tensor(self._policy_distances(offsets))
        threshold = self.task.config.world.success_threshold
        return int((final < threshold).sum()), -float(final.mean())

    def _snapshot(self) -> dict[str, Tensor]:
        return {k: v.detach().clone() for k, v in self.policy.state_dict().items()}

    def _refit(
        self, index: int, current: list[Labelled], offsets: list[tuple[float, float]], seed: int
    ) -> tuple[tuple[int, float], list[float] | None]:
        """Up to ``refits`` S-step refits at condition ``index`` from the best weights so far,
        while the policy misses one of ``offsets``; keeps the best by :meth:`_score`. Returns
        its score and the losses of the refit that produced it (None: the first fit stayed)."""
        best, state, kept = self._score(offsets), self._snapshot(), None
        for r in range(self.config.refits):
            if best[0] == len(offsets):
                break
            losses = self._distill(current, seed * 100 + 50 + r, self.config.refit_steps)
            score = self._score(offsets)
            record = {"condition": index, "event": "refit", "round": r, "successes": score[0]}
            self.log({**record, "of": len(offsets), "kept": score > best})
            if score > best:
                best, state, kept = score, self._snapshot(), losses
            else:
                self.policy.load_state_dict(state)
        return best, kept

    def _augmented(
        self,
        data: ConditionSamples,
        p_cur: LinearGaussian,
        p_pre: LinearGaussian | None,
        gen: torch.Generator,
        offset: tuple[float, float],
    ) -> DistillBatch:
        """``augment`` copies of D_g's states, each perturbed by ``augment_scale`` times the
        per-step spread of the condition's successes (in the dimensions ``augment_mode``
        says), labelled by its controllers."""
        x = data.x
        spread = (x - x.mean(0)).std(0)  # [T, dX]
        noise = torch.randn(self.config.augment, *x.shape, generator=gen, dtype=x.dtype)
        x_aug = (x + self.config.augment_scale * spread * noise.to(x.device)).flatten(0, 1)
        if self.config.augment_mode == "kinematic":
            x_aug = self._consistent(x_aug, offset)
        aug = ConditionSamples(
            x_aug, x_aug[..., :0], x_aug[..., 0], x_aug[:, 0, 0], *_targets(x_aug, p_cur, p_pre)
        )
        return aug.to_batch()

    def _consistent(self, x: Tensor, offset: tuple[float, float]) -> Tensor:
        """States ``[..., dX]`` with their points and point velocities recomputed from q and
        q-dot: ``p(q) - p*`` and ``J(q) q-dot``."""
        lay, kin = self.task.layout, self.task.kinematics
        q, qd = x[..., lay.q], x[..., lay.qd]
        points, jac = kin.points_and_jacobian(q)
        out = x.clone()
        out[..., lay.points] = (points - self.task.targets([offset])[0]).flatten(-2)
        out[..., lay.point_velocities] = (jac @ qd.unsqueeze(-1)).squeeze(-1)
        return out

    def _rollout_noiseless(self, p: LinearGaussian, offset: tuple[float, float]) -> float:
        zero = torch.zeros(
            1, self.task.T, self.task.layout.dU, dtype=torch.float64, device=self.task.device
        )
        return float(self.task.sample(linear_gaussian_actor(p, zero), [offset]).final_distance[0])

    def _policy_distances(self, offsets: list[tuple[float, float]]) -> list[float]:
        if not self.policy_trained:
            return [float("nan")] * len(offsets)
        return self.task.sample(policy_actor(self.policy), offsets).final_distance.tolist()

    # -- the stream ----------------------------------------------------------------------
    def run(
        self, conditions: list[tuple[float, float]], on_condition: Callable[[dict[str, Any]], None]
    ) -> list[dict[str, Any]]:
        """Learn every condition not yet completed in ``out``, checkpointing after each."""
        done = self._restore()
        for index, offset in enumerate(conditions):
            if index < done:
                continue
            entry = self.learn_condition(index, offset)
            self.summary.append(entry)
            on_condition(entry)
        final = self._policy_distances(list(conditions))
        for entry, dist in zip(self.summary, final, strict=True):
            entry["policy_final_distance_end"] = dist
            entry["policy_success_end"] = dist < self.task.config.world.success_threshold
        return self.summary

    def _checkpoint_dir(self, index: int) -> str:
        return os.path.join(self.out, "checkpoints", f"after_condition_{index:03d}")

    def _restore(self) -> int:
        """Resume after the last condition whose replay group was written (the replay is
        written last, so its policy checkpoint and summary entry exist)."""
        done = len(self.replay.conditions())
        if done == 0:
            return 0
        self.summary = []
        for index in range(done):
            with open(os.path.join(self._checkpoint_dir(index), "entry.json")) as fh:
                self.summary.append(json.load(fh))
        self.policy = GaussianPolicy.load(self._checkpoint_dir(done - 1), self.task.device)
        return done


def _concat(batches: list[DistillBatch]) -> DistillBatch:
    return DistillBatch(*(torch.cat(f) for f in zip(*batches, strict=True)))


def _write_json(path: str, data: Any) -> None:
    """Write JSON atomically (temp file, fsync, rename)."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def label_source(final: Labels, final_succeeds: bool, sampled: Labels | None) -> Labels:
    """The controllers (p_cur, p_pre) whose means and precisions label a condition's D_g,
    with the iteration at which that p_cur acts (the final one: the iteration count).

    The final p_cur, unless its own noiseless rollout misses; then the p_cur whose samples
    last succeeded (``sampled``), so that the policy never imitates a controller known to
    fail. With no such p_cur, the final one.
    """
    return final if final_succeeds or sampled is None else sampled


def _targets(
    x: Tensor, p_cur: LinearGaussian, p_pre: LinearGaussian | None
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Means and precisions of p_cur and p_pre at states ``x: [M, T, dX]`` (zeros and
    ``has_pre`` false without p_pre)."""
    with torch.no_grad():
        mean_cur, prec_cur = controller_targets(p_cur, x)
        if p_pre is not None:
            mean_pre, prec_pre = controller_targets(p_pre, x)
        else:
            mean_pre, prec_pre = torch.zeros_like(mean_cur), torch.zeros_like(prec_cur)
    has_pre = torch.full((x.shape[0],), p_pre is not None, dtype=torch.bool, device=x.device)
    return mean_cur, prec_cur, mean_pre, prec_pre, has_pre
