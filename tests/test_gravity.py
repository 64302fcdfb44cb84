"""Gravity compensation found missing from rollouts let go at the start pose, the learner's own
compensation at the simulator's boundary, and a condition learnt on an arm without one."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import torch
from conftest import ROOT, finish_script, start_script

from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.gravity import MARGIN, GravityConfig, estimate_gravity, let_go
from lolgps_torch.sim.plant import NOMINAL_PLANT, PlantConfig
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig

KUKA = "robots/kuka_peg.urdf"
PANDA = os.path.join(pybullet_data.getDataPath(), "franka_panda/panda.urdf")
FAR = (0.0, 2.0, -1.0)  # a hole out of the arm's way
UNCOMPENSATED = PlantConfig(gravity_compensation="none")


@pytest.fixture(scope="module", params=[KUKA, PANDA], ids=["kuka", "panda"])
def arm(request: pytest.FixtureRequest) -> ArmSpec:
    return load_arm(request.param)


def _start(arm: ArmSpec) -> np.ndarray:
    """A pose off the middle of the joints' limits, where gravity pulls every arm here."""
    return np.asarray(arm.lower) * 0.45 + np.asarray(arm.upper) * 0.55


def _let_go(
    arm: ArmSpec, config: WorldConfig, plant: PlantConfig = NOMINAL_PLANT
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """The probe's transitions let go at :func:`_start` in a world of ``plant``, and the
    joints' effective inertias there."""
    world = PegWorld(arm, config, FAR, plant=plant)
    try:
        world.set_hole((0.0, 0.0))
        q0 = _start(arm)
        return let_go(world, q0, GravityConfig()), world.effective_inertia(q0.tolist()).numpy()
    finally:
        world.close()


@pytest.mark.parametrize(
    "plant",
    [
        PlantConfig(),
        UNCOMPENSATED,
        PlantConfig(gravity_compensation="model", payload=1.0),
        PlantConfig(gravity_compensation="none", payload=1.0, inertia_scale=0.3),
        PlantConfig(obs_noise=0.001),
        PlantConfig(gravity_compensation="none", obs_noise=0.001, action_delay=0.05),
    ],
    ids=["nominal", "none", "payload", "none-reshaped", "noise", "none-noise-late"],
)
def test_the_probe_finds_whether_the_arm_compensates_gravity(
    arm: ArmSpec, plant: PlantConfig
) -> None:
    """Let go with zero commands, the arm without compensation falls as the URDF's model
    predicts and the compensated one stays put, with a clear margin either way: also with a
    payload or other inertias the plant does not tell, sensor noise and late commands."""
    config = WorldConfig()
    states, inertia = _let_go(arm, config, plant)
    estimate = estimate_gravity(states, arm, config, inertia)
    assert estimate.conclusive  # one residual under 1 / MARGIN of the other
    assert estimate.compensated == (plant.gravity_compensation != "none")
    rss = sorted([estimate.rss_none, estimate.rss_compensated])
    assert rss[1] > 2 * MARGIN * rss[0]


def test_speeds_neither_hypothesis_explains_are_taken_as_compensated() -> None:
    """Joint speeds half way between rest and the model's fall, which neither hypothesis
    explains better than the other: inconclusive, taken as compensated."""
    arm = load_arm(KUKA)
    config = WorldConfig()
    free = PlantConfig(limits="off")  # the fall's every step, a limit passed or not
    rest, inertia = _let_go(arm, config, free)
    fall, _ = _let_go(arm, config, dataclasses.replace(UNCOMPENSATED, limits="off"))
    lay = config.layout(arm.dof)
    drift = tuple(states.copy() for states in rest)  # half way between rest and the fall
    for states, still, falling in zip(drift, rest, fall, strict=True):
        states[..., lay.qd] = (still[..., lay.qd] + falling[..., lay.qd]) / 2
    estimate = estimate_gravity((drift[0], drift[1]), arm, config, inertia)
    assert estimate.compensated and not estimate.conclusive


def test_the_learners_compensation_is_the_urdfs_gravity_torque(arm: ArmSpec) -> None:
    """What the learner adds is g(q) of its own rigid-body model: PyBullet's inverse dynamics
    of the URDF at zero velocity and acceleration, at poses across the joints' range; on an arm
    without compensation it steps exactly as the arm compensated by its simulator."""
    config = dataclasses.replace(WorldConfig(), compensate_gravity=True)
    world = PegWorld(arm, config, FAR, plant=UNCOMPENSATED)
    rng = np.random.default_rng(0)
    try:
        world.set_hole((0.0, 0.0))
        zeros = [0.0] * len(world.movable)
        for fraction in rng.uniform(0.1, 0.9, (4, arm.dof)):
            q = np.asarray(arm.lower) + fraction * (np.asarray(arm.upper) - np.asarray(arm.lower))
            world.reset(q)
            states = pb.getJointStates(world.body, world.movable, physicsClientId=world.client)
            q_all = [s[0] for s in states]  # every moving joint, held ones included
            expected = pb.calculateInverseDynamics(
                world.body, q_all, zeros, zeros, physicsClientId=world.client
            )
            np.testing.assert_allclose(
                world.learner_compensation(),
                np.asarray(expected)[world.actuated_in_movable],
                rtol=1e-9,
                atol=1e-9,
            )
        compensated = PegWorld(arm, WorldConfig(), FAR)
        try:
            compensated.set_hole((0.0, 0.0))
            q0 = _start(arm)
            u = rng.normal(0.0, 1.0, (10, arm.dof))
            ours = np.stack([world.reset(q0), *(world.step(row) for row in u)])
            theirs = np.stack([compensated.reset(q0), *(compensated.step(row) for row in u)])
        finally:
            compensated.close()
    finally:
        world.close()
    np.testing.assert_allclose(ours, theirs, atol=1e-8)


def test_the_gravity_torque_is_the_rnea_at_rest_to_the_bit(arm: ArmSpec) -> None:
    """The first-moment form of g(q) the learner's compensation uses gives the full RNEA's
    numbers at zero velocity and acceleration, bit for bit (the RNEA's other terms are zeros)."""
    dynamics = ArmDynamics(arm, 9.81, "pybullet")
    q = torch.from_numpy(np.random.default_rng(1).uniform(-3.0, 3.0, (200, arm.dof)))
    zeros = torch.zeros_like(q)
    assert torch.equal(dynamics.gravity_torque(q), dynamics.inverse_dynamics(q, zeros, zeros))


def test_a_condition_without_gravity_compensation_is_found_and_learnt(tmp_path: Path) -> None:
    """No compensation, nothing said to the learner: ``train_condition.py`` finds it missing,
    says so, records it (config.json's task compensates, so evaluate.py and render.py rebuild
    the same arm) and inserts the peg."""
    out, log = tmp_path / "cond", tmp_path / "cond.log"
    command = ["python", str(ROOT / "scripts" / "train_condition.py"), "--urdf", str(ROOT / KUKA),
               "--hole", "0", "0", "--iterations", "4", "--stop-at-success", "--workers", "1",
               "--gravity-compensation", "none", "--out", str(out)]  # fmt: skip
    assert finish_script(start_script(command, log), log) == 0, log.read_text()[-2000:]
    assert "not compensated for gravity" in log.read_text()
    config = json.loads((out / "config.json").read_text())
    assert config["detected_gravity_compensation"] == "none"
    assert config["task"]["world"]["compensate_gravity"] is True
    assert config["task"]["plant"]["gravity_compensation"] == "none"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["noiseless_final_distance"] < 0.06
