"""Rollouts: N worlds stepped in lockstep, the actions computed for all N in one torch call;
or the rows of a batch (:func:`rollout_rows`), the form that worker processes share out, each
rollout's result its row's alone.

The only numpy in the algorithm path is here, at the simulator boundary: the state of each
world is read into one ``[N, dX]`` array, turned into a tensor, the acting controller maps it
to ``[N, dU]`` torques, and these go back to the worlds.

A matrix product's rows depend on how many rows it multiplies (its kernel differs), so a row
acted on in a batch may differ in the last bit from the same row alone. Where the engine steps
worlds together (:attr:`World.lockstep <lolgps_torch.sim.simulator.World.lockstep>`, MuJoCo)
and the actor has a row-wise form (:class:`Rowwise`: elementwise products and sums, no matrix
product), :func:`rollout_rows` steps a batch's rows together; otherwise each row runs alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.simulator import Simulator, World, WorldConfig
from lolgps_torch.types import LinearGaussian


class Rollouts(NamedTuple):
    """A batch's rollouts: states x ``[N, T+1, dX]`` (``x_T`` the state after the last action),
    actions u ``[N, T, dU]``, the final tip distance ``[N]`` (m) and whether the arm's
    controller stopped the rollout (``fault [N]`` bool: a limit passed, :attr:`World.fault
    <lolgps_torch.sim.simulator.World.fault>`)."""

    x: Tensor
    u: Tensor
    final: Tensor
    fault: Tensor


class Actor(Protocol):
    """``act(t, x, rows) -> u``: states ``x: [n, dX]`` of the batch's rollouts ``rows`` at step
    ``t`` -> torques ``[n, dU]``."""

    def __call__(self, t: int, x: Tensor, rows: slice, /) -> Tensor: ...


@runtime_checkable
class Rowwise(Protocol):
    """An actor with a row-wise form: the same actions, each row's computed by operations
    whose result for a row does not depend on the other rows of the call."""

    def rowwise(self) -> Actor:
        """The actor's row-wise form."""
        ...


def matmul_rows(x: Tensor, A: Tensor) -> Tensor:
    """``x @ A^T`` for ``x: [n, k]``, ``A: [m, k]``, as elementwise products summed over the
    last axis: each row's bits are the same whatever the other rows (tests/test_guard.py)."""
    return (A * x.unsqueeze(-2)).sum(-1)


class LinearGaussianActor(NamedTuple):
    """``u_t = K_t x_t + k_t + shifted_t`` for the batch's rows ``rows``; plain data, so that it
    can be sent to a worker process."""

    K: Tensor  # [T, dU, dX]
    k: Tensor  # [T, dU]
    shifted: Tensor  # [N, T, dU]: chol(cov_t) eps_t per rollout

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        return x @ self.K[t].T + self.k[t] + self.shifted[rows, t]

    def rowwise(self) -> Actor:
        return RowwiseLinearGaussian(self.K, self.k, self.shifted)


class RowwiseLinearGaussian(NamedTuple):
    """:class:`LinearGaussianActor` row-wise (:func:`matmul_rows`)."""

    K: Tensor  # [T, dU, dX]
    k: Tensor  # [T, dU]
    shifted: Tensor  # [N, T, dU]

    def __call__(self, t: int, x: Tensor, rows: slice) -> Tensor:
        return matmul_rows(x, self.K[t]) + self.k[t] + self.shifted[rows, t]


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
        self._build = (simulator, arm, config, nominal_mouth, plant)
        try:
            self.grow(n_worlds)
        except BaseException:
            self.close()
            raise

    @property
    def lockstep(self) -> bool:
        """Whether this engine steps a batch's rows together (:attr:`World.lockstep`)."""
        return self.worlds[0].lockstep

    def grow(self, n_worlds: int) -> None:
        """Build worlds until there are at least ``n_worlds``."""
        simulator, arm, config, nominal_mouth, plant = self._build
        while len(self.worlds) < n_worlds:
            self.worlds.append(build_world(simulator, arm, config, nominal_mouth, plant))

    def rollout(
        self,
        act: Actor,
        offsets: Sequence[tuple[float, float]],
        keys: Sequence[tuple[int, ...]] | None = None,
    ) -> Rollouts:
        """Run one episode of T actions per hole offset (:class:`Rollouts`, float64 tensors on
        the sampler's device, the faults bool). Rollout i's sensor noise is drawn from
        ``keys[i]`` (default ``(i,)``)."""
        keys = [(i,) for i in range(len(offsets))] if keys is None else keys
        parts = []
        for start in range(0, len(offsets), len(self.worlds)):
            chunk = list(offsets[start : start + len(self.worlds)])
            rows = slice(start, start + len(chunk))
            parts.append(self.episode(act, chunk, keys[rows], rows))
        return self._tensors(parts)

    def _tensors(self, parts: Sequence[tuple[np.ndarray, ...]]) -> Rollouts:
        """Episodes' arrays (:meth:`episode`) joined as :class:`Rollouts` on the device."""
        x, u, final, fault = (np.concatenate(field) for field in zip(*parts, strict=True))
        x_t, u_t, final_t = (
            torch.as_tensor(a, dtype=torch.float64, device=self.device) for a in (x, u, final)
        )
        return Rollouts(x_t, u_t, final_t, torch.as_tensor(fault, device=self.device))

    def episode(
        self,
        act: Actor,
        offsets: Sequence[tuple[float, float]],
        keys: Sequence[tuple[int, ...]],
        rows: slice,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One episode of the first ``len(offsets)`` worlds in lockstep, acted on by ``act``'s
        batch rows ``rows``: x ``[n, T+1, dX]``, u ``[n, T, dU]``, final distances ``[n]`` and
        faults ``[n]`` (:class:`Rollouts`)."""
        T = self.config.T
        worlds = self.worlds[: len(offsets)]
        step = type(worlds[0]).step_together
        for world, off in zip(worlds, offsets, strict=True):
            world.set_hole(off)
        x_np = np.stack([w.reset(self.q0, key) for w, key in zip(worlds, keys, strict=True)])
        xs = np.empty((len(worlds), T + 1, x_np.shape[1]))
        us = np.empty((len(worlds), T, len(self.q0)))
        for t in range(T):
            xs[:, t] = x_np
            x_t = torch.from_numpy(x_np).to(self.device)
            u_np = act(t, x_t, rows).cpu().numpy()
            us[:, t] = u_np
            x_np = step(worlds, u_np)
        xs[:, T] = x_np
        final = np.array([w.tip_distance() for w in worlds])
        return xs, us, final, np.array([w.fault is not None for w in worlds])

    def close(self) -> None:
        for w in self.worlds:
            w.close()


def rollout_rows(
    sampler: Sampler,
    act: Actor,
    offsets: Sequence[tuple[float, float]],
    rows: Sequence[int],
    batch: int = 0,
) -> Rollouts:
    """The rollouts of the batch's ``rows`` (row i at ``offsets[i]``), stacked as
    :meth:`Sampler.rollout` returns them; row i's sensor noise is keyed ``(batch, i)``.  Each
    run of consecutive rows is stepped together where the engine and the actor allow it (module
    docstring; ``sampler`` grows the worlds it needs), else each row runs alone in ``sampler``'s
    first world. A rollout's result depends on its row alone, not on which rows share the
    call, so any split of a batch over processes gives the same rollouts."""
    if not (sampler.lockstep and isinstance(act, Rowwise)):
        parts = [
            sampler.rollout(RowActor(act, row), [offsets[row]], [(batch, row)]) for row in rows
        ]
        return Rollouts(*(torch.cat(field) for field in zip(*parts, strict=True)))
    rowwise = act.rowwise()
    runs: list[list[int]] = []
    for row in rows:
        if runs and runs[-1][-1] + 1 == row:
            runs[-1].append(row)
        else:
            runs.append([row])
    sampler.grow(max(len(run) for run in runs))
    return sampler._tensors(
        [
            sampler.episode(
                rowwise,
                [offsets[r] for r in run],
                [(batch, r) for r in run],
                slice(run[0], run[-1] + 1),
            )
            for run in runs
        ]
    )
