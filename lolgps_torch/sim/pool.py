"""Rollouts shared out over worker processes, each holding a world of its own.

PyBullet steps a world on one core, so a batch of rollouts (an iteration's N samples, or the
policy's noiseless check at every learnt position) is split into ``workers`` contiguous blocks
of rows: the first for this process's own world, one for each spawned worker. Every rollout
runs alone (:func:`~lolgps_torch.sim.rollout.rollout_rows`), so the batch's result is the same
for any number of workers, one included.

A PyBullet client cannot be pickled: each worker builds its world from plain data
(:class:`WorldSetup`) when it starts, and receives the acting controller as plain data (the
actors of :mod:`lolgps_torch.sim.rollout` and :mod:`lolgps_torch.policy.actor` are named tuples
of tensors). The workers start with the pool, so they import and build their worlds while the
main process prepares its first batch, and they end with :meth:`RolloutPool.close` or with the
main process. They are spawned with the main script hidden (:func:`main_script_hidden`): they
import this module and what it needs, not the script's own imports.

Between batches a worker can run an errand (:meth:`RolloutPool.submit`): a picklable callable,
run where the worker would otherwise wait, whose result the main process collects later; a
batch sent to that worker meanwhile waits for the errand to finish.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.process
import multiprocessing.queues
import pickle
import queue
import sys
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.rollout import Actor, Rollouts, Sampler, rollout_rows
from lolgps_torch.sim.simulator import Simulator, WorldConfig

Position = tuple[float, float]
Errand = Callable[[], Any]  # picklable, its result too


@dataclass(frozen=True)
class WorldSetup:
    """What a worker needs to build a world identical to the main process's: the arm, the
    world settings, the placement's nominal hole mouth (m) and start pose (rad), the plant
    and the simulator."""

    arm: ArmSpec
    config: WorldConfig
    nominal_mouth: tuple[float, ...]
    q0: tuple[float, ...]
    plant: PlantConfig = PlantConfig()
    simulator: Simulator = "pybullet"

    def sampler(self) -> Sampler:
        """One world in this process."""
        return Sampler(
            self.arm, self.config, self.nominal_mouth, self.q0, 1, "cpu", self.plant, self.simulator
        )


def _failure(error: BaseException) -> BaseException:
    """``error`` as the main process will re-raise it: itself when it pickles (a
    :class:`LolgpsError` or a :class:`NumericalError` keeps its type), else a RuntimeError
    with the worker's traceback."""
    try:
        pickle.loads(pickle.dumps(error))
    except Exception:
        return RuntimeError("a rollout worker failed:\n" + traceback.format_exc())
    return error


@contextmanager
def main_script_hidden() -> Iterator[None]:
    """Hide the ``__main__`` module's file and spec while processes are spawned, so they do
    not re-run the main script. multiprocessing re-runs it in each spawned process, for pickled
    references into it; workers whose target and data come from this package need none, and a
    script that builds a task would cost each worker pytorch_kinematics' and yourdfpy's
    start-up, about a second."""
    main = sys.modules["__main__"]
    spec, path = main.__spec__, main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        yield
    finally:
        main.__spec__ = spec
        if path is not None:
            main.__file__ = path


def _next_job(jobs: multiprocessing.queues.Queue[bytes | None]) -> bytes | None:
    """The next job, or None once the main process asks to stop or has ended (a killed run's
    workers do not outlive it)."""
    parent = multiprocessing.parent_process()
    while True:
        try:
            return jobs.get(timeout=1.0)
        except queue.Empty:
            if parent is not None and not parent.is_alive():
                return None


def _serve(setup: WorldSetup, jobs: multiprocessing.queues.Queue[bytes | None],
           results: multiprocessing.queues.Queue[bytes]) -> None:  # fmt: skip
    """A worker: build the world, then run jobs until None, putting each one's result (or the
    exception that stopped it) on ``results``: an errand is called without arguments, an
    ``(actor, offsets, rows, batch)`` tuple is rolled out."""
    torch.set_num_threads(1)
    try:
        sampler: Sampler | None = setup.sampler()
        built: BaseException | None = None
    except Exception as error:  # reported with the first job, which is when the caller waits
        sampler, built = None, error
    while (job := _next_job(jobs)) is not None:
        try:
            task = pickle.loads(job)
            if callable(task):
                result: Any = task()
            elif sampler is None:
                raise built if built is not None else RuntimeError("no world")
            else:
                act, offsets, rows, batch = task
                result = rollout_rows(sampler, act, offsets, rows, batch)
        except Exception as error:
            result = _failure(error)
        results.put(pickle.dumps(result))
    if sampler is not None:
        sampler.close()


class RolloutPool:
    """This process's sampler and ``workers - 1`` spawned processes with a world each.

    :param setup: the worlds the workers build (the same as ``own``'s).
    :param workers: processes sharing a batch, this one included (at least 2).
    :param own: this process's sampler; its first world runs the first block of each batch.
    """

    def __init__(self, setup: WorldSetup, workers: int, own: Sampler) -> None:
        if workers < 2:
            raise LolgpsError(f"a rollout pool needs at least 2 workers, got {workers}")
        self.workers, self.own = workers, own
        self._procs: list[tuple[Any, Any, Any]] = []  # (process, jobs, results)
        self._errands: list[deque[int]] = [deque() for _ in range(workers - 1)]  # uncollected
        self._done: dict[int, Any] = {}  # errand -> its result, received before it was asked
        self._submitted = 0
        context = multiprocessing.get_context("spawn")
        with main_script_hidden():
            for _ in range(self.workers - 1):
                jobs, results = context.Queue(), context.Queue()
                proc = context.Process(target=_serve, args=(setup, jobs, results), daemon=True)
                proc.start()
                self._procs.append((proc, jobs, results))

    def rollout(self, act: Actor, offsets: Sequence[Position], batch: int = 0) -> Rollouts:
        """The batch's rollouts, row i at ``offsets[i]`` acted on by ``act``'s row i, as
        :func:`rollout_rows` returns them (CPU tensors)."""
        n = len(offsets)
        mine, *blocks = [b.tolist() for b in torch.arange(n).tensor_split(min(self.workers, n))]
        used = self._procs[: len(blocks)]
        for (_, jobs, _), rows in zip(used, blocks, strict=True):
            jobs.put(pickle.dumps((act, list(offsets), rows, batch)))
        try:  # while the workers roll out theirs
            own: Any = rollout_rows(self.own, act, offsets, mine, batch)
        except Exception as error:
            own = error
        parts = [own, *(self._receive_rollout(worker) for worker in range(len(used)))]
        failures = [p for p in parts if isinstance(p, BaseException)]
        if failures:
            raise failures[0]
        return Rollouts(*(torch.cat(field) for field in zip(*parts, strict=True)))

    def submit(self, errand: Errand) -> int:
        """Send ``errand`` to the last worker (whose block of a batch is the smallest), which
        runs it after the jobs it already has; returns the ticket :meth:`collect` takes."""
        ticket, self._submitted = self._submitted, self._submitted + 1
        worker = len(self._procs) - 1
        self._procs[worker][1].put(pickle.dumps(errand))
        self._errands[worker].append(ticket)
        return ticket

    def collect(self, ticket: int) -> Any:
        """The result of the errand :meth:`submit` returned ``ticket`` for, waiting for it;
        the exception that stopped it is raised here."""
        for worker, owed in enumerate(self._errands):
            while ticket in owed:
                self._receive_errand(worker)
        result = self._done.pop(ticket)
        if isinstance(result, BaseException):
            raise result
        return result

    def _receive_errand(self, worker: int) -> None:
        """Receive the result of ``worker``'s oldest uncollected errand."""
        proc, _, results = self._procs[worker]
        self._done[self._errands[worker].popleft()] = self._receive(proc, results)

    def _receive_rollout(self, worker: int) -> Any:
        """``worker``'s next rollout result, after the errands it was sent before it."""
        while self._errands[worker]:
            self._receive_errand(worker)
        proc, _, results = self._procs[worker]
        return self._receive(proc, results)

    @staticmethod
    def _receive(proc: multiprocessing.process.BaseProcess, results: Any) -> Any:
        """The worker's next result; a worker that died is a :class:`LolgpsError`."""
        while True:
            try:
                return pickle.loads(results.get(timeout=1.0))
            except queue.Empty:
                if not proc.is_alive():
                    raise LolgpsError(
                        f"a rollout worker process ended (exit status {proc.exitcode})"
                    ) from None

    def close(self) -> None:
        """Stop the workers (each closes its world)."""
        for proc, jobs, _ in self._procs:
            if proc.is_alive():
                jobs.put(None)
        for proc, _, _ in self._procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
        self._procs, self._errands, self._done = [], [], {}
