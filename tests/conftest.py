"""Fixtures shared across test modules, and how the suite runs in parallel.

The suite runs on pytest-xdist workers (``-n auto`` in pyproject.toml), each test process with
one torch thread: the workers are the parallelism, and a second intra-op thread per process
only spins against them (on a busy 2-core machine a C-step then takes several times as long).
The modules whose tests share an expensive fixture (``GROUPS``) each run on one worker, so the
fixture is built once; a shared fixture is also built once per test run under a file lock
(``shared_dir``), whichever worker asks first. (xdist's own ``--dist loadgroup`` does not group
under pytest 9, whose node ids xdist 3.8 cannot suffix: the grouping is done here, by
:func:`pytest_xdist_make_scheduler`.) The stand-in Franka's two runs of minutes (``FIRST``,
where selected) start first, one on each worker, then the groups (``GROUP_ORDER``), then the
longest tests (``LONGEST``), so that the short tests fill both workers' ends.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before torch is imported; inherited by subprocesses
os.environ["LOLGPS_WORKERS"] = "1"  # scripts roll out in their own process, as tests do

import fcntl
import json
import multiprocessing
import runpy
import sys
import warnings
from collections.abc import Callable
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any, NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMALL = [
    "--max-iterations",
    "7",
    "--success-phases",
    "1",
    "--distill-steps",
    "100",
    "--repairs",
    "0",
]
CONDITIONS = [[0.0, 0.0], [0.01, -0.01]]
# module -> the worker group its tests run in: those sharing the CI stream, and those on Ray
GROUPS = {"test_kill_resume.py": "ci_stream", "test_stream.py": "ci_stream", "test_ray.py": "ray"}
# before the groups where selected, one on each worker: the stand-in Franka's learning run and
# its kill and resume (-m franka), minutes of its server's real time each
FIRST = (
    "test_franka.py::test_learns_one_condition_then_evaluates_on_the_arm",
    "test_franka.py::test_killed_mid_rollout_then_resumed",
)
# the groups in the order they start: Ray's (its instance's start-up, under -m slow its sweep)
# before the CI stream's
GROUP_ORDER = ("ray", "ci_stream")
# the longest tests outside the groups, longest first: those of -m slow (the identification's
# fits), then those of the default suite (seconds each in a run of the whole suite
# on the loaded 2-core machine: 28, 24, 22, 21, 18, 17, 15, 15, 14, 13, 12 and less)
LONGEST = (
    "test_identify.py::test_the_step_residual_starts_from_the_torque_balances_estimate",
    "test_identify.py::test_the_compensations_share_stays_between_the_two_models",
    "test_identify.py::test_a_transition_the_model_does_not_describe_pulls_the_fit_by_little",
    "test_identify.py::test_sensor_noise_biases_the_torque_balance_not_the_speed_residuals",
    "test_identify.py::test_recovers_link_masses",
    "test_faults.py::test_a_numerical_failure_fails_its_condition_and_the_stream_goes_on",
    "test_faults.py::test_a_full_disk_stops_the_run_with_one_error_and_the_run_resumes",
    "test_mujoco.py::test_ci_stream_learns_in_mujoco",
    "test_limits.py::test_a_ci_sized_run_learns_one_condition_within_the_limits",
    "test_identify.py::test_the_learner_reports_the_identified_arm_on_unseen_rollouts",
    "test_cli.py::test_fuzzed_numeric_flags_are_accepted_or_refused_before_writing",
    "test_gravity.py::test_a_condition_without_gravity_compensation_is_found_and_learnt",
    "test_urdf_fuzz.py::test_mutations_are_refused_or_survive_a_rollout",
    "test_mjcf.py::test_ci_stream_learns_with_an_mjcf_arm",
    "test_workers.py::test_iterations_are_the_same_for_one_and_two_workers",
    "test_batch.py::test_mdgps_c_step_is_anchored_to_the_policy_linearisation",
    "test_arms.py::test_arm_on_a_base_or_torso_or_small_loads_places_and_iterates[rtb-al5d]",
    "test_workers.py::test_rollouts_are_the_same_for_one_and_two_workers",
    "test_plan.py::test_a_planned_start_worse_than_holding_still_is_dropped_for_the_hold",
    "test_latency.py::test_a_stream_with_late_commands_finds_the_delay_and_learns",
)


def _group(nodeid: str) -> str | None:
    return GROUPS.get(nodeid.split("::")[0].rsplit("/", 1)[-1])


def _rank(item: pytest.Item) -> int:
    """Where ``item`` starts: the first ones, the groups, then the longest tests, each in
    order, then the rest."""
    name = item.nodeid.rsplit("/", 1)[-1]
    group = _group(item.nodeid)
    order = [*(name.startswith(first) for first in FIRST),
             *(group == other for other in GROUP_ORDER),
             *(name.startswith(long) for long in LONGEST)]  # fmt: skip
    return order.index(True) if True in order else len(order)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_rank)


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """xdist's scope scheduling with a group per entry of ``GROUPS`` and a scope per other
    test; the scopes go out in the order :func:`pytest_collection_modifyitems` sorted them
    into (not xdist's, largest scope first: a group would go before ``FIRST``)."""
    from xdist.scheduler import LoadScopeScheduling

    config.option.loadscopereorder = False

    class GroupScheduling(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            return _group(nodeid) or nodeid

    return GroupScheduling(config, log)


def shared_dir(
    tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]
) -> Path:
    """``<root>/<name>``, built by ``build(path)`` once per test run: under xdist ``<root>`` is
    the directory all workers' temporary directories share, and the first worker to ask
    builds it while holding a lock the others wait on."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    path = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / f"{name}.done").exists():
            path.mkdir(exist_ok=True)
            build(path)
            (root / f"{name}.done").touch()
    return path


def ci_stream_command(tmp: Path, out: Path) -> list[str]:
    """The CI-sized stream (two conditions, small limits, one on-policy round after the first
    fit) into ``out``."""
    conditions = tmp / "conditions.json"
    conditions.write_text(json.dumps(CONDITIONS))
    script = str(ROOT / "scripts" / "run_stream.py")
    urdf = str(ROOT / "robots" / "kuka_peg.urdf")
    return [sys.executable, script, "--urdf", urdf, "--conditions", str(conditions), *SMALL,
            "--onpolicy-rounds", "1", "--out", str(out)]  # fmt: skip


def _script_main(script: str, args: list[str], log: str) -> None:
    """``python SCRIPT ARGS`` with both output streams to the file ``log``."""
    stream = open(log, "a")  # noqa: SIM115 (this process ends with the script)
    os.dup2(stream.fileno(), 1)
    os.dup2(stream.fileno(), 2)
    sys.stdout = sys.stderr = stream
    sys.argv = [script, *args]
    runpy.run_path(script, run_name="__main__")


def start_script(command: list[str], log: Path) -> BaseProcess:
    """``command`` (``[python, script, *args]``) started as a fork of this process, where the
    imports a new interpreter would spend seconds on are done; its output goes to ``log``, its
    ``exitcode`` is the script's exit status once it ends."""
    process = multiprocessing.get_context("fork").Process(
        target=_script_main, args=(command[1], command[2:], str(log))
    )
    process.start()
    return process


def finish_script(process: BaseProcess, log: Path, timeout: float = 900) -> int:
    """Wait for a script from :func:`start_script`: its exit status, a failure with the end of
    ``log`` if it does not end within ``timeout`` seconds."""
    process.join(timeout)
    if process.exitcode is None:
        process.kill()
        process.join()
        pytest.fail(f"{process.name} did not end in {timeout} s: {log.read_text()[-2000:]}")
    return process.exitcode


def _run_ci_stream(tmp: Path) -> None:
    log = tmp / "run.log"
    code = finish_script(start_script(ci_stream_command(tmp, tmp / "run"), log), log)
    assert code == 0, log.read_text()[-2000:]


@pytest.fixture(scope="session")
def ci_stream(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One uninterrupted run of the CI-sized stream for the whole suite: ``<tmp>/run``."""
    return shared_dir(tmp_path_factory, "ci_stream", _run_ci_stream)


class ScriptRun(NamedTuple):
    """How a script ended: its exit status and what it wrote to stdout and stderr."""

    code: int
    out: str
    err: str


@pytest.fixture
def run_script(capfd: pytest.CaptureFixture[str]) -> Callable[..., ScriptRun]:
    """``run_script(path, *args)`` runs ``python path ARGS`` (``path`` relative to the
    repository) in this process, where the imports a new process would spend seconds on are
    already done, and reports what the file descriptors 1 and 2 received. Each warning is
    shown once per run, as in a new process, however often earlier tests in this process
    raised it."""

    def run(path: str, *args: str) -> ScriptRun:
        script = str(ROOT / path)
        capfd.readouterr()
        argv = sys.argv
        sys.argv = [script, *args]
        try:
            with warnings.catch_warnings():  # new filters: the warnings already shown forgotten
                warnings.simplefilter("default")
                runpy.run_path(script, run_name="__main__")
            code = 0
        except SystemExit as exit_:
            code = exit_.code if isinstance(exit_.code, int) else int(exit_.code is not None)
        finally:
            sys.argv = argv
        out, err = capfd.readouterr()
        return ScriptRun(code, out, err)

    return run


def fk_gap(task: Any, poses: int = 5) -> float:
    """Largest |pytorch-kinematics - PyBullet| peg point difference (m) of a ``PegTask`` at
    random poses."""
    import numpy as np
    import torch

    world, arm, rng = task.sampler.worlds[0], task.arm, np.random.default_rng(0)
    worst = 0.0
    for _ in range(poses):
        q = rng.uniform(arm.lower, arm.upper)
        world.reset(q)
        fk = task.kinematics.points(torch.tensor(q)).numpy()
        worst = max(worst, float(np.abs(fk - world.points()).max()))
    return worst


def check_published_arm(
    urdf: str,
    dof: int,
    ee_link: str | None = None,
    chain: tuple[str | None, str | None] = (None, None),
    scale: float | None = None,
) -> None:
    """A published description as published: ``dof`` actuated joints (ending at ``ee_link``,
    if given; on the chain the flags ``--base-link`` and ``--ee-link`` pick, ``chain``, where
    given), kinematics agreeing with PyBullet's at random poses,
    every position of the paper stream (scaled by ``scale``, or to the arm where it does not
    fit, as ``--scale auto`` does, when None) reachable from the placed hole (one batched IK; test_world checks
    ``PegTask.check_reachable`` itself), and one short iteration of the local learner."""
    import warnings

    import numpy as np
    import torch

    from lolgps_torch.arm_probes import fit_scale, scaled
    from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
    from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
    from lolgps_torch.robot.ik import follow, generic_rank, solve_ik_batch
    from lolgps_torch.robot.placement import PlacementConfig, reach
    from lolgps_torch.robot.validate import ArmWarning
    from lolgps_torch.sim.world import WorldConfig
    from lolgps_torch.task import PegTask, TaskConfig

    placement = PlacementConfig(positions=tuple(default_training_stream(AreaConfig(), 0)[0]))
    config = TaskConfig(
        urdf=urdf,
        base_link=chain[0],
        ee_link=chain[1],
        world=WorldConfig(T=10),
        placement=placement,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        config = fit_scale(config)[0] if scale is None else scaled(config, scale)
        task = PegTask(config, n_worlds=2)
    stream = config.placement.positions
    try:
        assert task.arm.dof == dof
        assert ee_link is None or task.arm.ee_link == ee_link
        assert fk_gap(task) < 1e-6
        _, error = solve_ik_batch(task.kinematics, task.arm, task.targets(list(stream)), margin=0.0)
        assert float(error.max()) <= placement.ik_tolerance
        # and from the start pose, continuously, as a controller would move (ik.follow)
        rank = generic_rank(task.kinematics, task.q0 + 0.1 * torch.randn(8, task.arm.dof))
        error, least = follow(task.kinematics, task.arm, task.q0, task.targets(list(stream)), rank)
        assert float(error.max()) <= placement.ik_tolerance
        assert float(least.min()) >= placement.dexterity * reach(task.arm, task.kinematics)[1]
        learner = LocalLearner(task, stream[0], LocalConfig(samples=2), seed=0)
        samples, _, record = iterate(learner, learner.p_cur, None, False, (0, 0, 0.0))
        assert torch.isfinite(samples.cost).all() and np.isfinite(record.mean_cost)
    finally:
        task.close()
