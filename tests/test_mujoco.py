"""The MuJoCo world (``--sim mujoco``): its arm's dynamics against the torch rigid-body model,
its state and free motion against PyBullet's world, a CI-sized stream that learns in it, and
the one-line refusals."""

from __future__ import annotations

import cProfile
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import torch
from conftest import ROOT, SMALL, ScriptRun

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim import simulator
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.sim.rollout import Rowwise, linear_gaussian_actor, rollout_rows
from lolgps_torch.sim.simulator import WorldConfig
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import LinearGaussian

mujoco = pytest.importorskip("mujoco")
from lolgps_torch.sim.mujoco_compat import mass_matrix  # noqa: E402
from lolgps_torch.sim.mujoco_world import LINK_DAMPING, MujocoWorld, link_damping  # noqa: E402

ARMS = {
    "kuka": str(ROOT / "robots" / "kuka_peg.urdf"),
    "panda": os.path.join(pybullet_data.getDataPath(), "franka_panda", "panda.urdf"),
}
FAR = (5.0, 5.0, -3.0)  # a hole mouth far from the arm: free space


@pytest.fixture(scope="module", params=sorted(ARMS))
def arm(request: pytest.FixtureRequest) -> ArmSpec:
    return load_arm(ARMS[request.param])


def test_mass_matrix_and_bias_forces_match_the_rigid_body_model(arm: ArmSpec) -> None:
    """MuJoCo's compiled arm has the torch model's M(q) (mass_matrix) and c(q, qd) + g(q)
    (qfrc_bias) at random states."""
    world = build_world("mujoco", arm, WorldConfig(), FAR)
    m, d = world.model, mujoco.MjData(world.model)
    dyn = ArmDynamics(arm)
    rng = np.random.default_rng(0)
    for _ in range(8):
        q = rng.uniform(arm.lower, arm.upper)
        qd = rng.normal(size=arm.dof)
        d.qpos[world.qpos_ids], d.qvel[world.dof_ids] = q, qd
        mujoco.mj_forward(m, d)
        M = mass_matrix(m, d)[np.ix_(world.dof_ids, world.dof_ids)]
        bias = d.qfrc_bias[world.dof_ids]
        T = torch.as_tensor
        expected_M = dyn.mass_matrix(T(q)).numpy()
        expected_bias = dyn.inverse_dynamics(T(q), T(qd), T(np.zeros(arm.dof))).numpy()
        np.testing.assert_allclose(M, expected_M, rtol=0, atol=1e-9 * np.abs(expected_M).max())
        np.testing.assert_allclose(bias, expected_bias, rtol=0, atol=1e-9 * np.abs(bias).max())
    world.close()


def _smooth_torques(inertia: np.ndarray, rng: np.random.Generator, steps: int) -> np.ndarray:
    """``m_j a_j(t)``: sums of two sinusoids of 0.3 rad/s^2 accelerations per joint, scaled by
    each joint's effective inertia m_j (free motion of a few 0.1 rad)."""
    t = np.arange(steps)[:, None] * WorldConfig().dt
    n = len(inertia)
    freq, phase = rng.uniform(2.0, 5.0, (2, n)), rng.uniform(0, 2 * np.pi, (2, n))
    return inertia * 0.3 * (np.sin(freq[0] * t + phase[0]) + np.sin(freq[1] * t + phase[1]))


def test_state_and_free_rollout_match_pybullet(arm: ArmSpec) -> None:
    """The same state layout and start state as PyBullet's world; one control step changes the
    joint velocities as PyBullet's does to 1e-3, and 20 steps of the same torques stay within
    1e-3 rad and 1 mm of PyBullet's (close, not identical: measured 1e-10 rad on the KUKA,
    1e-4 rad on the Panda).  Contact is where the engines differ; the stream below learns
    with MuJoCo's."""
    config = WorldConfig()
    worlds = [build_world(name, arm, config, FAR) for name in ("pybullet", "mujoco")]
    lower, upper = np.asarray(arm.lower), np.asarray(arm.upper)
    q0 = lower + np.random.default_rng(1).uniform(0.4, 0.6, arm.dof) * (upper - lower)
    inertia = worlds[0].effective_inertia(q0).numpy()
    torques = _smooth_torques(inertia, np.random.default_rng(2), 20)
    runs = []
    for world in worlds:
        states = [world.reset(q0)]
        states += [world.step(u) for u in torques]
        runs.append(np.stack(states))
        world.close()
    pybullet, mujoco_run = runs
    n, lay = arm.dof, config.layout(arm.dof)
    assert pybullet.shape == mujoco_run.shape == (21, lay.dX)
    np.testing.assert_allclose(mujoco_run[0], pybullet[0], rtol=0, atol=1e-6)
    first = np.abs(mujoco_run[1, lay.qd] - pybullet[1, lay.qd]).max()
    assert first < 1e-3 * max(1.0, np.abs(pybullet[1, lay.qd]).max())
    assert np.abs(mujoco_run[:, :n] - pybullet[:, :n]).max() < 1e-3
    assert np.abs(mujoco_run[:, lay.points] - pybullet[:, lay.points]).max() < 1e-3


def _old_link_damping(world: MujocoWorld) -> np.ndarray:
    """Bullet's link damping written out body by body with numpy's cross and matrix products,
    independently of :func:`link_damping`: wrenches ``[B, 2, 3]`` of the arm's bodies."""
    m, d = world.model, world.data
    arm = range(1, m.body("lolgps_hole").id)
    root = d.subtree_com[m.body_rootid[1]]
    k, out = LINK_DAMPING, []
    for b in arm:
        w, v0 = d.cvel[b, :3], d.cvel[b, 3:]
        v = v0 + np.cross(w, d.xipos[b] - root)
        R = d.ximat[b].reshape(3, 3)
        Iw = R @ np.diag(m.body_inertia[b]) @ R.T @ w
        mass = m.body_mass[b]
        out.append([-k * (1 + np.linalg.norm(v)) * mass * v, -k * (1 + np.linalg.norm(w)) * Iw])
    return np.array(out)


def test_link_damping_matches_its_definition_body_by_body() -> None:
    """In a moving arm, :func:`link_damping` (all bodies in a few numpy calls) gives each body
    the wrench of Bullet's definition computed body by body, to rounding."""
    # torques this large pass the joints' speed limits: the plant without its reflex
    unlimited = PlantConfig(limits="off")
    task = PegTask(TaskConfig(urdf=ARMS["kuka"], sim="mujoco", plant=unlimited), n_worlds=1)
    world = task.sampler.worlds[0]
    assert isinstance(world, MujocoWorld)
    world.reset(np.asarray(task.geometry.q0))
    rng = np.random.default_rng(3)
    for _ in range(5):
        world.step(rng.normal(0.0, 20.0, task.arm.dof))
    mujoco.mj_step1(world.model, world.data)  # positions and velocities, as the step has them
    expected = _old_link_damping(world)
    got = link_damping(world._cvel, world._com, world._root_com, world._R, world._mass,
                       world._inertia)  # fmt: skip
    assert np.abs(expected).max() > 1e-3  # the arm moves
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    task.close()


def test_rows_stepped_together_equal_each_row_alone_bit_for_bit() -> None:
    """A batch of 5 rollouts at different holes under noisy linear-Gaussian controllers,
    stepped together (the rows' actions in one call, the worlds' physics steps together),
    gives each row the same bits as the row rolled out alone, and as any split of the rows
    (the form worker processes share); the row-wise actions equal the matrix products' to
    rounding."""
    task = PegTask(TaskConfig(urdf=ARMS["kuka"], sim="mujoco"), n_worlds=1)
    T, dX, dU = task.T, task.layout.dX, task.arm.dof
    g = torch.Generator().manual_seed(0)
    eye = torch.eye(dU, dtype=torch.float64)
    K = 0.05 * torch.randn(T, dU, dX, dtype=torch.float64, generator=g)
    K[..., :dU] -= 20.0 * eye  # hold the start pose, per unit of each joint's inertia
    K[..., dU : 2 * dU] -= 6.0 * eye
    K = task.effective_inertia()[:, None] * K
    k = -K[..., :dU] @ task.q0
    noise = torch.randn(5, T, dU, dtype=torch.float64, generator=g)
    cov = torch.diag(task.effective_inertia() ** 2).expand(T, dU, dU)
    act = linear_gaussian_actor(LinearGaussian(K, k, cov), noise)
    offsets = [(0.02 * i - 0.04, 0.01 * i) for i in range(5)]
    assert task.sampler.lockstep and isinstance(act, Rowwise)
    together = rollout_rows(task.sampler, act, offsets, range(5), batch=3)
    assert len(task.sampler.worlds) == 5  # grown for the batch
    split = [rollout_rows(task.sampler, act, offsets, rows, 3) for rows in ([0], [1, 2], [3, 4])]
    alone = [rollout_rows(task.sampler, act, offsets, [row], 3) for row in range(5)]
    for parts in (split, alone):
        for field, whole in zip(zip(*parts, strict=True), together, strict=True):
            assert torch.equal(torch.cat(field), whole)
    x, u, _, fault = together
    assert not fault.any()  # the arms stayed within their limits
    assert x[:, -1, task.layout.qd].abs().max() > 0.01  # the arms moved
    matmul = torch.einsum("tuv,ntv->ntu", K, x[:, :-1]) + k + act.shifted
    torch.testing.assert_close(u, matmul, rtol=0, atol=1e-12 * float(matmul.abs().max()))
    task.close()


def test_stream_profile_counts_the_rollouts_and_steps_of_each_simulator(
    tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """``stream_profile.py --summarise`` reads profiles of 3 rollouts of 20 steps on each
    simulator (stepped together in MuJoCo, one at a time in PyBullet): 3 resets, 60 commands,
    and time in the physics steps and the linear-Gaussian actor."""
    T, dU = 20, 7
    for sim in ("pybullet", "mujoco"):
        task = PegTask(TaskConfig(urdf=ARMS["kuka"], sim=sim, world=WorldConfig(T=T)), n_worlds=1)
        K = torch.zeros(T, dU, task.layout.dX, dtype=torch.float64)
        cov = torch.eye(dU, dtype=torch.float64).expand(T, dU, dU)
        act = linear_gaussian_actor(LinearGaussian(K, torch.zeros(T, dU, dtype=torch.float64),
                                                   cov), torch.zeros(3, T, dU, dtype=torch.float64))  # fmt: skip
        profiler = cProfile.Profile(time.process_time)
        profiler.runcall(rollout_rows, task.sampler, act, [(0.0, 0.0)] * 3, range(3))
        profiler.dump_stats(tmp_path / f"{sim}.prof")
        task.close()
    result = run_script("scripts/research/stream_profile.py", "--out", str(tmp_path),
                        "--summarise")  # fmt: skip
    assert result.code == 0, result.err
    rows = {line[:28].strip(): line[28:].split() for line in result.out.splitlines()[1:]}
    assert [float(v) for v in rows["rollouts"][:2]] == [3, 3]
    assert [float(v) for v in rows["control steps"][:2]] == [3 * T, 3 * T]
    for part in ("physics steps", "linear-Gaussian actor"):
        assert all(float(v) > 0 for v in rows[part][:2])


def test_the_table_stops_the_peg_as_in_pybullet() -> None:
    """Pushed down by 30 N beside the hole, the peg's tip comes to rest on the table in MuJoCo
    within 3 mm of where it does in PyBullet; on the way its soft contact (time constant 4
    physics steps) lets it dip at most 12 mm into the table, where PyBullet stops it above."""
    # a push this hard passes the joints' speed limits: the plant without its reflex
    task = PegTask(TaskConfig(urdf=ARMS["kuka"], plant=PlantConfig(limits="off")), n_worlds=1)
    lay, depth = task.layout, task.config.world.depth
    lowest, rest = {}, {}
    for name in ("pybullet", "mujoco"):
        world = build_world(name, task.arm, task.config.world, task.geometry.nominal_mouth,
                            task.config.plant)  # fmt: skip
        world.set_hole((0.1, 0.0))  # the table under the peg
        x = world.reset(np.asarray(task.geometry.q0))
        heights = []
        for _ in range(60):
            _, jacobian = task.kinematics.points_and_jacobian(torch.as_tensor(x[lay.q]))
            x = world.step(-30.0 * jacobian[2].numpy())  # the tip's z row
            heights.append(x[lay.points][2])  # above the hole's floor
        world.close()
        lowest[name], rest[name] = min(heights), heights[-1]
    task.close()
    assert depth - 0.012 < lowest["mujoco"]  # the table's surface is at depth
    assert depth < lowest["pybullet"] < depth + 0.005
    assert abs(rest["mujoco"] - rest["pybullet"]) < 0.003


def test_ci_stream_learns_in_mujoco(tmp_path: Path, run_script: Callable[..., ScriptRun]) -> None:
    """The CI-sized stream at one condition in MuJoCo: the local controller and the policy
    insert the peg, and the run records the simulator; ``evaluate.py --sim pybullet`` tests
    the policy in the other simulator, and ``render.py`` films it in the run's."""
    conditions = tmp_path / "conditions.json"
    conditions.write_text(json.dumps([[0.0, 0.0]]))
    out = tmp_path / "run"
    result = run_script("scripts/run_stream.py", "--urdf", ARMS["kuka"], "--sim", "mujoco",
                        "--conditions", str(conditions), *SMALL, "--workers", "1",
                        "--distill-steps", "1000",  # a policy fitted as by default
                        "--out", str(out))  # fmt: skip
    assert result.code == 0, result.err[-2000:]
    assert json.loads((out / "config.json").read_text())["task"]["sim"] == "mujoco"
    (entry,) = json.loads((out / "summary.json").read_text())["conditions"]
    assert entry["local_success"]
    assert entry["policy_final_distance_end"] < WorldConfig().success_threshold
    evaluated = run_script("scripts/evaluate.py", "--run", str(out), "--positions",
                           str(conditions), "--workers", "1", "--sim", "pybullet")  # fmt: skip
    assert evaluated.code == 0, evaluated.err[-2000:]
    assert json.loads((out / "eval.json").read_text())["sim"] == "pybullet"
    video = tmp_path / "policy.gif"
    rendered = run_script("scripts/render.py", "--run", str(out), "--out", str(video),
                          "--size", "64", "48", "--every", "50")  # fmt: skip
    assert rendered.code == 0, rendered.err[-2000:]
    assert video.stat().st_size > 0


def test_plant_variations_and_a_missing_engine_are_one_line_errors(
    monkeypatch: pytest.MonkeyPatch, run_script: Callable[..., ScriptRun], tmp_path: Path
) -> None:
    result = run_script("scripts/run_stream.py", "--urdf", ARMS["kuka"], "--sim", "mujoco",
                        "--payload", "0.5", "--out", str(tmp_path / "run"))  # fmt: skip
    assert result.code == 2
    assert result.err.startswith("error: --sim mujoco simulates the arm as its URDF")
    assert not (tmp_path / "run").exists()
    find_spec = simulator.importlib.util.find_spec
    monkeypatch.setattr(simulator.importlib.util, "find_spec",
                        lambda name, *rest: None if name == "mujoco" else find_spec(name, *rest))  # fmt: skip
    result = run_script("scripts/run_stream.py", "--urdf", ARMS["kuka"], "--sim", "mujoco",
                        "--out", str(tmp_path / "run"))  # fmt: skip
    assert result.code == 2
    assert result.err == (
        "error: --sim mujoco needs MuJoCo, which is not installed: pip install -e '.[mujoco]'\n"
    )
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("version", "accepted"),
    [("3.3.6", False), ("3.3.7", True), ("3.8.0", True), ("3.17.0", True), ("4.0.0", False),
     ("4.0.1", True), ("4.3.2rc1", True), ("5.0.0", False)],
)  # fmt: skip
def test_mujoco_releases_from_3_3_7_up_to_4_x_are_taken_but_4_0_0(
    monkeypatch: pytest.MonkeyPatch, version: str, accepted: bool
) -> None:
    monkeypatch.setattr(simulator.importlib.metadata, "version", lambda name: version)
    if accepted:
        simulator.require("mujoco")
        return
    with pytest.raises(LolgpsError) as refused:
        simulator.require("mujoco")
    assert str(refused.value) == (
        f"--sim mujoco needs MuJoCo 3.3.7 up to 4.x (not 4.0.0), found {version}: "
        "pip uninstall -y mujoco && pip install -e '.[mujoco]'"
    )


def test_a_mujoco_that_does_not_import_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 4.x upgraded in place over a 3.x may have lost files to the old release's uninstall:
    the error says so and how to reinstall."""
    import_module = simulator.importlib.import_module

    def broken(name: str, *rest: str) -> object:
        if name == "mujoco":
            raise ImportError("libmujoco.so.4.0.1: cannot open shared object file\nmore")
        return import_module(name, *rest)

    monkeypatch.setattr(simulator.importlib, "import_module", broken)
    with pytest.raises(LolgpsError) as refused:
        simulator.require("mujoco")
    version = simulator.importlib.metadata.version("mujoco")
    assert str(refused.value) == (
        f"MuJoCo {version} is installed but does not import (libmujoco.so.4.0.1: cannot open "
        "shared object file): pip uninstall -y mujoco && pip install -e '.[mujoco]'"
    )
