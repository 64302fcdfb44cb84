"""Rollouts: N worlds stepped in lockstep, the actions computed for all N in one torch call;
or each rollout alone (:func:`rollout_rows`), the form that worker processes share out.

The only numpy in the algorithm path is here, at the simulator boundary: the state of each
world is read into one ``[N, dX]`` array, turned into a tensor, the acting controller maps it
to ``[N, dU]`` torques, and these go back to the worlds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

import numpy as np
import torch
from torch import Tensor

from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.simulator import Simulator, World, WorldConfig
from lolgps_torch.types import LinearGaussian


class Actor(Protocol):
    """``act(t, x, rows) -> u``: states ``x: [n, dX]`` of the batch's rollouts ``rows`` at step
    ``t`` -> torques ``[n, dU]``."""

    def __call__(self, t: int, x: Tensor, rows: slice, /) -> Tensor: ...


class LinearGaussianActor(NamedTuple):
    """``u_t = K_t x_t + k_t + shifted_t`` for the batch's rows ``rows``; plain data, so that it
    can be sent to a worker process."""

    K: Tensor  # [T, dU, dX]
    k: Tensor  # [T, dU]
    shifted: Tensor  # [N, T, dU]: chol(cov_t) eps_t per rollout

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        return x @ self.K[t].T + self.k[t] + self.shifted[rows, t]


def linear_gaussian_actor(controller: LinearGaussian, noise: Tensor) -> Actor:
    """``u_t = K_t x_t + k_t + chol(cov_t) eps_t`` with pre-drawn noise ``eps: [N, T, dU]``."""
    L = controller.chol().detach()
    shifted = torch.einsum("tuv,ntv->ntu", L, noise)  # [N, T, dU]
    return LinearGaussianActor(controller.K.detach(), controller.k.detach(), shifted)


class RowActor(NamedTuple):
    """Row ``row`` of a batch's actor, acting alone in a one-rollout batch."""

    actor: Actor
    row: int

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        return self.actor(t, x, slice(self.row, self.row + 1))


class Sampler:
    """A pool of worlds (of the plant ``plant``, stepped by ``simulator``) that run up to
    ``len(worlds)`` rollouts at a time."""

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        q0: Sequence[float],
        n_worlds: int,
        device: torch.device | str = "cpu",
        plant: PlantConfig = NOMINAL_PLANT,
        simulator: Simulator = "pybullet",
    ) -> None:
        self.config = config
        self.q0 = np.asarray(q0, dtype=np.float64)
        self.device = torch.device(device)
        self.worlds: list[World] = []
        try:
            for _ in range(n_worlds):
                self.worlds.append(build_world(simulator, arm, config, nominal_mouth, plant))
        except BaseException:
            self.close()
            raise

    def rollout(
        self,
        act: Actor,
        offsets: Sequence[tuple[float, float]],
        keys: Sequence[tuple[int, ...]] | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Run one episode of T actions per hole offset; returns the states x ``[N, T+1, dX]``
        (``x_T`` the state after the last action), u ``[N, T, dU]`` and the final tip distance
        ``[N]`` (float64 tensors on the sampler's device). Rollout i's sensor noise is drawn
        from ``keys[i]`` (default ``(i,)``)."""
        T = self.config.T
        keys = [(i,) for i in range(len(offsets))] if keys is None else keys
        results_x, results_u, results_d = [], [], []
        for start in range(0, len(offsets), len(self.worlds)):
            chunk = list(offsets[start : start + len(self.worlds)])
            worlds = self.worlds[: len(chunk)]
            for world, off in zip(worlds, chunk, strict=True):
                world.set_hole(off)
            x_np = np.stack([w.reset(self.q0, keys[start + i]) for i, w in enumerate(worlds)])
            xs = np.empty((len(chunk), T + 1, x_np.shape[1]))
            us = np.empty((len(chunk), T, len(self.q0)))
            for t in range(T):
                xs[:, t] = x_np
                x_t = torch.from_numpy(x_np).to(self.device)
                u_np = act(t, x_t, slice(start, start + len(chunk))).cpu().numpy()
                us[:, t] = u_np
                x_np = np.stack([w.step(u) for w, u in zip(worlds, u_np, strict=True)])
            xs[:, T] = x_np
            results_x.append(xs)
            results_u.append(us)
            results_d.append([w.tip_distance() for w in worlds])
        return (
            torch.as_tensor(np.concatenate(results_x), dtype=torch.float64, device=self.device),
            torch.as_tensor(np.concatenate(results_u), dtype=torch.float64, device=self.device),
            torch.as_tensor(np.concatenate(results_d), dtype=torch.float64, device=self.device),
        )

    def close(self) -> None:
        for w in self.worlds:
            w.close()


def rollout_rows(
    sampler: Sampler,
    act: Actor,
    offsets: Sequence[tuple[float, float]],
    rows: Sequence[int],
    batch: int = 0,
) -> tuple[Tensor, Tensor, Tensor]:
    """The rollouts of the batch's ``rows`` (row i at ``offsets[i]``), each run alone in
    ``sampler``'s first world, stacked as :meth:`Sampler.rollout` returns them; row i's sensor
    noise is keyed ``(batch, i)``. A rollout's result depends on its row alone, not on which
    rows share the call, so any split of a batch over processes gives the same rollouts."""
    parts = [sampler.rollout(RowActor(act, row), [offsets[row]], [(batch, row)]) for row in rows]
    x, u, final = (torch.cat(field) for field in zip(*parts, strict=True))
    return x, u, final
