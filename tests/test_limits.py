"""The arm's limits: the reflex that stops the simulated arm where a joint passes a limit, as a
real arm's controller does (both engines), faults counted as failures while the run goes on,
velocity limits derived where a URDF gives none, and the speed term of the cost."""

from __future__ import annotations

import dataclasses
import json
import re
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT, SMALL, ScriptRun

from lolgps_torch.lolgps.local import moved
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.effort import JOINT_SPEED, TIP_SPEED, joint_levers
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.validate import ArmWarning
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.reflex import POSITION_MARGIN, Reflex
from lolgps_torch.sim.simulator import World
from lolgps_torch.task import PegTask, TaskConfig, load_task_arm

KUKA = str(ROOT / "robots" / "kuka_peg.urdf")
SIMS = ["pybullet", pytest.param("mujoco", marks=pytest.mark.skipif(
    __import__("importlib").util.find_spec("mujoco") is None, reason="needs the mujoco extra"))]  # fmt: skip


@pytest.fixture(scope="module")
def task() -> Iterator[PegTask]:
    task = PegTask(TaskConfig(urdf=KUKA), n_worlds=2)
    yield task
    task.close()


def _world(task: PegTask, sim: str, velocity: float | None, limits: str = "reflex") -> World:
    """A world of ``sim`` with the task's arm, every joint's velocity limit ``velocity``
    (None: the URDF's)."""
    arm = task.arm
    if velocity is not None:
        arm = dataclasses.replace(arm, velocity=(velocity,) * arm.dof)
    return build_world(
        sim, arm, task.config.world, task.geometry.nominal_mouth, PlantConfig(limits=limits)
    )


def _push(world: World, q0: np.ndarray, steps: int) -> np.ndarray:
    """The last joint's speed after each of ``steps`` control steps of a constant torque on
    it, from rest at ``q0``."""
    world.reset(q0)
    u = np.zeros(len(q0))
    u[-1] = 2.0
    dof = len(q0)
    return np.array([abs(world.step(u)[dof + dof - 1]) for _ in range(steps)])


@pytest.mark.parametrize("sim", SIMS)
def test_the_reflex_fires_at_the_velocity_limit_and_not_below_it(task: PegTask, sim: str) -> None:
    q0 = np.asarray(task.geometry.q0)
    free = _world(task, sim, None, limits="off")
    speeds = _push(free, q0, 6)  # rising: the joint accelerates from rest
    free.close()
    assert np.all(np.diff(speeds) > 0)
    # a limit between the speeds after control steps 3 and 4 is passed within step 4 (index 3)
    limited = _world(task, sim, 0.5 * (speeds[2] + speeds[3]))
    reached = _push(limited, q0, 6)
    assert limited.fault is not None and "at step 3" in limited.fault
    assert "joint 7" in limited.fault and "velocity limit" in limited.fault
    np.testing.assert_allclose(reached[:3], speeds[:3], rtol=1e-9)
    assert np.all(reached[3:] == 0.0)  # braked where it stopped, and held there
    held = limited.observe()[: task.arm.dof].copy()
    limited.step(np.full(task.arm.dof, 50.0))
    np.testing.assert_array_equal(limited.observe()[: task.arm.dof], held)
    limited.reset(q0)
    assert limited.fault is None  # a new rollout starts anew
    limited.close()
    above = _world(task, sim, 1.001 * speeds[-1])  # the speed only ever rises within a step
    np.testing.assert_allclose(_push(above, q0, 6), speeds, rtol=1e-9)
    assert above.fault is None
    above.close()


@pytest.mark.parametrize("sim", SIMS)
def test_the_reflex_fires_near_a_position_limit_and_not_further_away(
    task: PegTask, sim: str
) -> None:
    world = _world(task, sim, None)
    joint = 3
    for gap, faults in ((0.5 * POSITION_MARGIN, True), (5 * POSITION_MARGIN, False)):
        q = np.asarray(task.geometry.q0, dtype=np.float64).copy()
        q[joint] = task.arm.upper[joint] - gap
        world.reset(q)
        for _ in range(3):
            world.step(np.zeros(task.arm.dof))
        assert (world.fault is not None) == faults, world.fault
        if faults:
            assert world.fault is not None and f"joint {joint + 1} at" in world.fault
    world.close()


def test_a_continuous_joint_has_no_position_limit(task: PegTask) -> None:
    free = dataclasses.replace(task.arm, unbounded=(task.arm.joint_names[6],))
    reflex = Reflex.of(free)
    assert np.isinf(reflex.lower[6]) and np.isinf(reflex.upper[6])
    assert reflex.upper[0] == pytest.approx(task.arm.upper[0] - POSITION_MARGIN)
    q = np.asarray(task.geometry.q0, dtype=np.float64).copy()
    q[6] = 100.0  # many turns of a continuous joint
    assert reflex.violation(q, np.zeros(7), 0) is None


def test_a_fault_is_a_failure_and_its_rollout_is_no_evidence_of_the_dynamics(
    task: PegTask,
) -> None:
    def act(t: int, x: torch.Tensor, rows: slice) -> torch.Tensor:
        u = torch.zeros(x.shape[0], 7, dtype=torch.float64)
        if rows.start == 0:  # row 0 only is flung
            u[:, 6] = 30.0
        return u

    samples = task.sample(act, [(0.0, 0.0), (0.0, 0.0)])
    assert samples.fault.tolist() == [True, False]
    assert not bool(samples.success[0])
    assert samples.scored_distance[0] == float("inf")
    assert samples.scored_distance[1] == samples.final_distance[1]
    kept = moved(samples)
    assert kept.N == 1 and not bool(kept.fault.any())
    assert moved(kept._replace(fault=torch.ones(1, dtype=torch.bool))).N == 1  # all stopped


def test_velocity_limits_are_derived_where_the_urdf_gives_none(tmp_path: Path) -> None:
    text = re.sub(r'velocity="[0-9.]+"', 'velocity="0"', Path(KUKA).read_text())
    path = tmp_path / "no_speeds.urdf"
    path.write_text(text)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        arm = load_arm(str(path))
    assert sum("velocity is not given" in str(w.message) for w in caught) == 7
    assert all(issubclass(w.category, ArmWarning) for w in caught)
    published = load_arm(KUKA)
    assert arm.effort == published.effort  # the efforts given stay as they are
    levers = joint_levers(arm)
    expected = torch.clamp(TIP_SPEED / levers, max=JOINT_SPEED)
    torch.testing.assert_close(torch.tensor(arm.velocity, dtype=torch.float64), expected)
    # the first joint turns about the vertical axis through the base: its lever is the tip's
    # largest horizontal distance from that axis, by pytorch-kinematics over random poses
    gen = torch.Generator().manual_seed(1)
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in (arm.lower, arm.upper))
    q = lo + (hi - lo) * torch.rand(4096, 7, generator=gen, dtype=torch.float64)
    tip = PegKinematics(arm).points(q)[:, 0]
    horizontal = float(tip[:, :2].norm(dim=-1).max())
    assert float(levers[0]) == pytest.approx(horizontal, rel=0.03)
    assert all(0.0 < v <= JOINT_SPEED for v in arm.velocity)
    assert 'velocity="0"' not in arm.urdf_text  # the copy a run keeps has them too


def test_velocity_limit_flag(task: PegTask, run_script: Callable[..., ScriptRun]) -> None:
    for bad in (["0"], ["-1"], ["nan"]):
        result = run_script("scripts/run_stream.py", "--urdf", KUKA, "--velocity-limit", *bad)
        assert result.code == 2
        assert result.err.strip().startswith("error:") and len(result.err.strip().splitlines()) == 1
    result = run_script("scripts/run_stream.py", "--urdf", KUKA, "--velocity-limit", "1", "2")
    assert result.code == 2 and "one per actuated joint" in result.err
    config = TaskConfig(urdf=KUKA, velocity_limit=(1.25,))
    assert load_task_arm(config).velocity == (1.25,) * 7


def _one_condition(tmp_path: Path, *flags: str) -> list[str]:
    conditions = tmp_path / "one.json"
    conditions.write_text(json.dumps([[0.0, 0.0]]))
    return ["--urdf", KUKA, "--conditions", str(conditions), *SMALL, *flags]


def test_a_ci_sized_run_learns_one_condition_within_the_limits(
    tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """The condition is learnt; its teachers (D_g) move within every velocity limit and the
    policy's noiseless check draws no fault (a fault never counts as reaching the hole). An
    exploring sample may fault: a peg pressed onto the table beside the hole can slip faster
    than a joint may move, and the reflex stops it, as on a real arm."""
    out = tmp_path / "run"
    # a policy fitted as by default, with its repair rounds while the condition is missed
    flags = ("--distill-steps", "1000", "--repairs", "6", "--out", str(out))
    result = run_script("scripts/run_stream.py", *_one_condition(tmp_path, *flags))
    assert result.code == 0, result.err
    (entry,) = json.loads((out / "summary.json").read_text())["conditions"]
    assert entry["local_success"] and entry["policy_success_after"]
    assert entry["faults"] < entry["rollouts"] / 2
    loaded = load_run(out)
    velocity = torch.tensor(load_task_arm(loaded.info.task).velocity, dtype=torch.float64)
    (record,) = loaded.records
    qd = loaded.info.task.world.layout(len(velocity)).qd
    speeds = record.samples.x[..., qd].abs() / velocity
    assert float(speeds.max()) <= 1.0


def test_faults_are_counted_and_the_run_goes_on(
    tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    out = tmp_path / "run"
    # without the guard, which keeps the samples within the limits too
    flags = ("--velocity-limit", "0.05", "--max-iterations", "2", "--no-guard", "--out", str(out))
    result = run_script("scripts/run_stream.py", *_one_condition(tmp_path, *flags))
    assert result.code == 0, result.err
    summary = json.loads((out / "summary.json").read_text())
    (entry,) = summary["conditions"]
    assert entry["faults"] > 0
    assert f"faults {entry['faults']}" in result.out
    # every rollout on the arm stopped at a limit is counted by kind: the samples' are its
    # faults, and the policy's checks and visits are counted beside them
    assert entry["arm_faults"]["sample"] == entry["faults"]
    assert summary["arm_faults"]["total"] == sum(entry["arm_faults"].values())
    assert set(entry["arm_faults"]) == set(entry["arm_rollouts"]) == {"sample", "probe", "visit"}
    assert f"{sum(entry['arm_faults'].values())} stopped at a limit" in result.out
    assert "arm_seconds" not in summary and entry["arm_seconds"] is None  # a simulator
