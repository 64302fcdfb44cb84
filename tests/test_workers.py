"""Rollouts spread over worker processes (``--workers``): the same results as in one process."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import ScriptRun

from lolgps_torch.controllers import smoothed_noise
from lolgps_torch.errors import NumericalError
from lolgps_torch.lolgps import plans
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, initial_controller, iterate
from lolgps_torch.lolgps.plans import PlannedStarts
from lolgps_torch.policy import GaussianPolicy, PolicyConfig, policy_actor
from lolgps_torch.sim.rollout import LinearGaussianActor, linear_gaussian_actor
from lolgps_torch.task import PegTask, TaskConfig

ROOT = Path(__file__).resolve().parents[1]
OFFSETS = [(0.0, 0.0), (0.01, -0.01), (-0.02, 0.02)]


@pytest.fixture(scope="module")
def tasks() -> Iterator[tuple[PegTask, PegTask]]:
    config = TaskConfig(str(ROOT / "robots" / "kuka_peg.urdf"))
    one, two = PegTask(config, workers=1), PegTask(config, workers=2)
    yield one, two
    one.close()
    two.close()


def test_rollouts_are_the_same_for_one_and_two_workers(tasks: tuple[PegTask, PegTask]) -> None:
    one, two = tasks
    noise = smoothed_noise(3, one.T, one.layout.dU, 2.0, torch.Generator().manual_seed(3))
    policy = GaussianPolicy(one.layout.dX, one.layout.dU, PolicyConfig(), one.device)
    policy.trained = True
    actors = [
        linear_gaussian_actor(initial_controller(one, LocalConfig()), noise),
        policy_actor(policy, one.model, noise),
        policy_actor(policy, one.model),
    ]
    for actor in actors:
        a, b = one.sample(actor, OFFSETS), two.sample(actor, OFFSETS)
        assert a.x.abs().sum() > 0 and not torch.equal(a.x[0], a.x[1])  # distinct rollouts
        for field in ("x", "u", "cost", "final_distance", "final_state"):
            assert torch.equal(getattr(a, field), getattr(b, field)), field


def test_iterations_are_the_same_for_one_and_two_workers(
    tasks: tuple[PegTask, PegTask],
) -> None:
    """Sampling, the dynamics fit and the C-step, twice (from the hold: the plan's own tests
    follow): the controllers agree bit for bit."""
    controllers = []
    for task in tasks:
        learner = LocalLearner(task, (0.01, 0.0), LocalConfig(model_plans=0), seed=7)
        for i in range(2):
            iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
        controllers.append(learner.p_cur)
    assert torch.equal(controllers[0].K, controllers[1].K)
    assert torch.equal(controllers[0].k, controllers[1].k)


def counted_plans(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Count the first controllers planned in this process (not the workers') from now on."""
    calls: list[int] = []
    inline = plans.planned_controller

    def counting(*args: Any) -> Any:
        calls.append(1)
        return inline(*args)

    monkeypatch.setattr(plans, "planned_controller", counting)
    return calls


def test_a_first_controller_planned_on_a_worker_is_the_one_planned_here(
    tasks: tuple[PegTask, PegTask], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Requested before a batch of rollouts (an S-step's closed-loop check), the plan on the
    idle worker is taken by the condition's learner, bit for bit the plan made in this
    process; the batch gets its own rollouts meanwhile."""
    task, config, offset = tasks[1], LocalConfig(model_plans=2), (0.01, -0.01)
    inline = LocalLearner(task, offset, config, seed=0)
    starts, calls = PlannedStarts(task, config), counted_plans(monkeypatch)
    starts.request(offset)
    zero = torch.zeros(3, task.T, task.layout.dU, dtype=torch.float64)
    actor = linear_gaussian_actor(initial_controller(task, config), zero)
    assert torch.equal(task.sample(actor, OFFSETS).x, tasks[0].sample(actor, OFFSETS).x)
    ahead = LocalLearner(task, offset, config, seed=0, planner=starts.plan)
    assert not calls  # planned by the worker
    assert all(torch.equal(a, b) for a, b in zip(ahead.p_cur, inline.p_cur, strict=True))
    assert ahead.start_cost == inline.start_cost


def test_a_first_controller_is_planned_here_where_the_worker_cannot_give_it(
    tasks: tuple[PegTask, PegTask], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A failure in the worker (here: asked for 0 torch threads), a plan requested for another
    condition, and one worker: each condition's plan is made in this process, the same."""
    config, offset = LocalConfig(model_plans=2), (0.0, 0.01)
    inline = LocalLearner(tasks[1], offset, config, seed=0)
    starts, calls = PlannedStarts(tasks[1], config), counted_plans(monkeypatch)
    with monkeypatch.context() as patched:
        patched.setattr(torch, "get_num_threads", lambda: 0)
        starts.request(offset)
    failed = LocalLearner(tasks[1], offset, config, seed=0, planner=starts.plan)
    starts.request((0.02, 0.0))
    elsewhere = LocalLearner(tasks[1], offset, config, seed=0, planner=starts.plan)
    one = PlannedStarts(tasks[0], config)
    one.request(offset)
    alone = LocalLearner(tasks[0], offset, config, seed=0, planner=one.plan)
    assert len(calls) == 3 and one.pool is None
    for learner in (failed, elsewhere, alone):
        assert all(torch.equal(a, b) for a, b in zip(learner.p_cur, inline.p_cur, strict=True))
        assert learner.start_cost == inline.start_cost
    zero = torch.zeros(2, tasks[1].T, tasks[1].layout.dU, dtype=torch.float64)
    actor = linear_gaussian_actor(inline.p_cur, zero)
    assert tasks[1].sample(actor, OFFSETS[:2]).x.isfinite().all()  # the pool still works


def test_a_blow_up_in_a_worker_is_the_numerical_error_of_the_batch(
    tasks: tuple[PegTask, PegTask],
) -> None:
    task = tasks[1]
    actor = linear_gaussian_actor(
        initial_controller(task, LocalConfig()),
        torch.zeros(2, task.T, task.layout.dU, dtype=torch.float64),
    )
    bad = LinearGaussianActor(actor.K, torch.full_like(actor.k, float("nan")), actor.shifted)
    with pytest.raises(NumericalError, match="non-finite action"):
        task.sample(bad, OFFSETS[:2])
    assert task.sample(actor, OFFSETS[:2]).x.isfinite().all()  # the pool still works


def test_workers_flag_is_checked_before_any_work(
    tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    result = run_script("scripts/run_stream.py", "--workers", "0", "--out", str(tmp_path / "run"))
    assert result.code == 2
    assert result.err.strip().splitlines() == ["error: --workers 0: must be at least 1"]
