"""The rollouts of an evaluation, spread over processes.

Rollouts are cut into fixed batches (:class:`Job`) and shared between this process and spawned
workers, each claiming the next unclaimed job. Each batch always holds the same positions and
a rollout does not depend on what its world ran before, so the results do not depend on the
number of workers. Only plain data crosses processes: this process builds the
:class:`PegTask` and scores every rollout; a worker (:mod:`lolgps_torch.evaluation.worker`)
receives the task's arm, world settings, placement and the policies' weights, builds its own
worlds (a PyBullet client cannot be pickled) and returns states, actions and final distances.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.queues
import queue
from collections.abc import Iterator, Sequence
from multiprocessing.process import BaseProcess
from typing import NamedTuple

import torch

from lolgps_torch.cluster import import_ray, ray_connection
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.worker import (
    Failure,
    Job,
    PolicyRoller,
    PolicyState,
    Rollouts,
    RolloutSetup,
    SetupRoller,
    next_job,
    run_worker,
)
from lolgps_torch.progress import Bar
from lolgps_torch.sim.franka import SIMULATED, RealArmConfig
from lolgps_torch.sim.pool import main_script_hidden
from lolgps_torch.sim.rollout import Rollouts as SimRollouts
from lolgps_torch.task import PegTask, TaskConfig


class JobResult(NamedTuple):
    """Per position of a :class:`Job`: final tip distance (m), total cost, success, and the
    peak joint speed as a fraction of the joint's velocity limit, ``max_{t,j} |q-dot_j| /
    v_j`` (above 1: a joint exceeded its limit), and whether the arm's controller stopped
    the rollout at a limit (a fault, never a success)."""

    final_distance: list[float]
    total_cost: list[float]
    success: list[bool]
    peak_speed: list[float]
    fault: list[bool]


def _score(task: PegTask, job: Job, rollouts: Rollouts) -> JobResult:
    """Per position of ``job``: final tip distance, total cost ``sum_t l(x_t, u_t)`` and
    success, by :meth:`PegTask.score`, and the peak joint speed over the velocity limits."""
    rolled = SimRollouts(*(torch.from_numpy(a) for a in rollouts))
    with torch.no_grad():
        scored = task.score(rolled, job.positions)
    limits = torch.tensor(task.arm.velocity, dtype=rolled.x.dtype)
    speed = (rolled.x[..., task.layout.qd].abs() / limits).amax(dim=(1, 2))
    return JobResult(
        scored.final_distance.tolist(),
        scored.cost.sum(dim=1).tolist(),
        scored.success.tolist(),
        speed.tolist(),
        scored.fault.tolist(),
    )


def _unpack(item: tuple[int, Rollouts | Failure]) -> tuple[int, Rollouts]:
    """A worker's ``(job index, rollouts)``; its failure raised here (a user error as one
    :class:`LolgpsError` line, a bug as a :class:`RuntimeError` with its traceback)."""
    index, result = item
    if isinstance(result, Failure):
        if result.user_error:
            raise LolgpsError(result.message)
        raise RuntimeError(f"an evaluation worker failed:\n{result.message}")
    return index, result


def _ready(
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]],
) -> Iterator[tuple[int, Rollouts]]:
    """The workers' results already queued, without waiting for more."""
    while True:
        try:
            item = results.get_nowait()
        except queue.Empty:
            return
        yield _unpack(item)


def _collect(
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]],
    missing: set[int],
    processes: Sequence[BaseProcess],
) -> Iterator[tuple[int, Rollouts]]:
    """The workers' results for the job indices ``missing``, as they arrive; raises
    :class:`LolgpsError` if every worker has died with some still missing."""
    while missing:
        try:
            item = results.get(timeout=0.5)
        except queue.Empty:
            if not any(p.is_alive() for p in processes) and results.empty():
                codes = [p.exitcode for p in processes]
                raise LolgpsError(f"evaluation workers died (exit codes {codes})") from None
            continue
        index, rollouts = _unpack(item)
        missing.discard(index)
        yield index, rollouts


def _setup(peg: PegTask, n_worlds: int, policies: Sequence[PolicyState]) -> RolloutSetup:
    """What a worker needs to run ``policies`` in worlds identical to ``peg``'s."""
    geometry = peg.geometry
    world = peg.config.world
    return RolloutSetup(
        peg.arm,
        world,
        geometry.nominal_mouth,
        geometry.q0,
        n_worlds,
        tuple(policies),
        peg.config.plant,
        peg.config.sim,
    )


def run_jobs(
    task: TaskConfig,
    policies: Sequence[PolicyState],
    jobs: Sequence[Job],
    workers: int,
    n_worlds: int,
    real: RealArmConfig = SIMULATED,
) -> list[JobResult]:
    """Results of ``jobs``, in order, from ``workers`` processes: this one and ``workers - 1``
    spawned ones, all on one torch thread, each claiming the next unclaimed job (on a real
    arm, ``real``, this process alone).

    This process starts the workers, builds ``task`` with ``n_worlds`` worlds, sends the
    workers its arm, world settings and placement and the ``policies`` the jobs name
    (:class:`RolloutSetup`), then rolls out jobs itself at once. The workers only
    build worlds and run policies (start-up: 2-3 CPU-seconds, mostly importing torch; the
    task's inverse kinematics and cost are not theirs) and send back states, actions and final
    distances. This process scores every rollout with the task's cost as :meth:`PegTask.sample`
    does (the workers' as they arrive, between its own jobs), so the results do not depend on
    ``workers``."""
    if workers < 1:
        raise LolgpsError(f"need at least one worker, got {workers}")
    context = multiprocessing.get_context("spawn")
    counter = context.Value("q", 0)
    setups: multiprocessing.queues.Queue[RolloutSetup] = context.Queue()
    results: multiprocessing.queues.Queue[tuple[int, Rollouts | Failure]] = context.Queue()
    processes = [
        context.Process(target=run_worker, args=(setups, list(jobs), counter, results))
        for _ in range(min(workers, len(jobs)) - 1)
        if real.arm == "simulated"
    ]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    peg = None
    try:
        with main_script_hidden():
            for process in processes:
                process.start()  # the workers import while this process builds the task
        peg = PegTask(task, n_worlds=n_worlds, real=real)
        roller = PolicyRoller(peg.sampler, peg.model, policies)
        for _ in processes:
            setups.put(_setup(peg, n_worlds, policies))
        found: dict[int, JobResult] = {}
        bar = Bar(len(jobs), "evaluation")
        while (index := next_job(counter, len(jobs))) is not None:
            ready = [(index, roller(jobs[index])), *_ready(results)]
            found.update((i, _score(peg, jobs[i], rollouts)) for i, rollouts in ready)
            bar.update(len(ready))
        for i, rollouts in _collect(results, set(range(len(jobs))) - set(found), processes):
            found[i] = _score(peg, jobs[i], rollouts)
        bar.close()
        return [found[i] for i in range(len(jobs))]
    finally:
        for process in processes:
            process.terminate()  # those still starting up when every job was taken
            process.join()
        if peg is not None:
            peg.close()
        torch.set_num_threads(threads)


def run_jobs_on_ray(
    task: TaskConfig,
    policies: Sequence[PolicyState],
    jobs: Sequence[Job],
    address: str | None,
    num_cpus: int,
    n_worlds: int,
) -> list[JobResult]:
    """Results of ``jobs``, in order, from Ray actors of one CPU each (one per CPU of the
    cluster at ``address``, or of a local instance of ``num_cpus`` CPUs when None): each
    builds its worlds once from the task's :class:`RolloutSetup` and runs the jobs it is
    given, one at a time; this process checks the policies against the task first and scores
    every rollout as :func:`run_jobs` does, so the results are the same."""
    ray = import_ray()
    with ray_connection(ray, address, num_cpus) as slots:
        peg = PegTask(task, n_worlds=n_worlds)
        try:
            PolicyRoller(peg.sampler, peg.model, policies)  # the policies' sizes, checked here
            roller = ray.remote(num_cpus=1)(SetupRoller)
            setup = ray.put(_setup(peg, n_worlds, policies))
            actors = [roller.remote(setup) for _ in range(max(1, min(slots, len(jobs))))]
            waiting = list(enumerate(jobs))
            pending = {actor.roll.remote(*waiting.pop(0)): actor for actor in actors if waiting}
            found: dict[int, JobResult] = {}
            bar = Bar(len(jobs), "evaluation")
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                actor = pending.pop(ref)
                index, rollouts = ray.get(ref)
                found[index] = _score(peg, jobs[index], rollouts)
                bar.update(1)
                if waiting:
                    pending[actor.roll.remote(*waiting.pop(0))] = actor
            bar.close()
            return [found[i] for i in range(len(jobs))]
        finally:
            peg.close()
