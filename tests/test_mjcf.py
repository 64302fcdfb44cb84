"""Arms described only in MJCF (``--mjcf FILE``, robot/mjcf.py): a five-joint arm written
here, with a joint anchored off its body's origin, a turned body, a joint ``ref``, a site
for the end effector and three kinds of torque limit, read as the URDF the package uses and
checked against MuJoCo's own model of the file; it steps in the MuJoCo world and a CI-sized
stream learns with it.  Files that cannot be converted, and ``--mjcf`` with PyBullet, are
one-line errors."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL, ScriptRun

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.mjcf import mjcf_urdf
from lolgps_torch.sim.engines import build_world
from lolgps_torch.sim.simulator import WorldConfig

mujoco = pytest.importorskip("mujoco")
from lolgps_torch.sim.mujoco_compat import mass_matrix  # noqa: E402

ARM = """<mujoco model="five">
  <default><joint damping="0.5"/><geom type="capsule" size="0.04"/></default>
  <worldbody>
    <body name="base">
      <geom type="cylinder" size="0.08 0.05" mass="4"/>
      <body name="link1" pos="0 0 0.1">
        <joint name="j1" axis="0 0 1" range="-170 170"/>
        <geom fromto="0 0 0 0 0 0.3" mass="3"/>
        <body name="link2" pos="0 0 0.3" quat="0.7071068 0.7071068 0 0">
          <joint name="j2" axis="0 0 1" range="-120 120" pos="0 0 0.01" ref="10"/>
          <geom fromto="0 0 0 0 0.4 0" mass="2.5"/>
          <body name="link3" pos="0 0.4 0">
            <joint name="j3" axis="0 0 1" range="-150 150"/>
            <geom fromto="0 0 0 0 0.35 0" mass="1.5"/>
            <body name="link4" pos="0 0.35 0" euler="-90 0 0">
              <joint name="j4" axis="0 1 0" range="-120 120"/>
              <geom fromto="0 0 0 0 0 0.1" mass="0.8"/>
              <body name="link5" pos="0 0 0.1">
                <joint name="j5" axis="0 0 1" range="-170 170"/>
                <geom fromto="0 0 0 0.02 0 0.08" mass="0.5"/>
                <site name="tool" pos="0 0 0.1"/>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor joint="j1" ctrlrange="-150 150"/>
    <motor joint="j2" gear="100" ctrlrange="-1.5 1.5"/>
    <motor joint="j3" forcerange="-60 60" forcelimited="true"/>
    <motor joint="j4" ctrlrange="-30 30"/>
    <motor joint="j5" ctrlrange="-10 10"/>
  </actuator>
</mujoco>
"""


@pytest.fixture(scope="module")
def arm_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("mjcf") / "five.xml"
    path.write_text(ARM)
    return path


def test_the_urdf_is_the_mjcf_arm(arm_file: Path) -> None:
    """At random joint angles and speeds, MuJoCo's compiler puts the URDF's tool link where the
    MJCF puts the site, and gives the URDF the MJCF's M(q) and bias forces c(q, qd) + g(q)
    (test_mujoco.py checks the torch model against MuJoCo's of a URDF); the torque limits
    come from the actuators, the ranges from the joints less their ``ref``."""
    arm = load_arm(str(arm_file), "tool", mjcf=True)
    assert arm.joint_names == ("j1", "j2", "j3", "j4", "j5")
    assert arm.effort == (150.0, 150.0, 60.0, 30.0, 10.0)
    np.testing.assert_allclose(arm.lower[1], np.radians(-130.0))
    source = mujoco.MjModel.from_xml_path(str(arm_file))
    keep_links = '<mujoco><compiler fusestatic="false"/></mujoco></robot>'
    text = mjcf_urdf(str(arm_file)).replace("</robot>", keep_links)
    converted = mujoco.MjModel.from_xml_string(text)
    d_source, d_converted = mujoco.MjData(source), mujoco.MjData(converted)
    rng, matrices = np.random.default_rng(0), []
    for _ in range(5):
        q = rng.uniform(arm.lower, arm.upper)
        d_source.qpos[:] = q + source.qpos0
        d_converted.qpos[:] = q
        d_source.qvel[:] = d_converted.qvel[:] = rng.normal(size=arm.dof)
        mujoco.mj_forward(source, d_source)
        mujoco.mj_forward(converted, d_converted)
        np.testing.assert_allclose(
            d_converted.xpos[converted.body("tool").id],
            d_source.site_xpos[source.site("tool").id],
            atol=1e-9,
        )
        for model, data in ((source, d_source), (converted, d_converted)):
            matrices.append(mass_matrix(model, data))
        np.testing.assert_allclose(matrices[-1], matrices[-2], atol=1e-9)
        np.testing.assert_allclose(d_converted.qfrc_bias, d_source.qfrc_bias, atol=1e-9)


def test_the_mjcf_arm_steps_in_mujoco(arm_file: Path) -> None:
    """The converted arm, with its peg on the site, builds and steps in the MuJoCo world."""
    arm = load_arm(str(arm_file), "tool", mjcf=True)
    world = build_world("mujoco", arm, WorldConfig(), (5.0, 5.0, -3.0))
    x = world.reset(np.full(arm.dof, 0.2))
    for _ in range(5):
        x = world.step(np.full(arm.dof, 0.5))
    assert np.isfinite(x).all() and not np.allclose(x[: arm.dof], 0.2)
    world.close()


def test_ci_stream_learns_with_an_mjcf_arm(
    arm_file: Path, tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """``run_stream.py --mjcf FILE --ee-link SITE --sim mujoco`` at one condition: the run's
    folder keeps the converted URDF, which ``evaluate.py`` reads back."""
    conditions = tmp_path / "conditions.json"
    conditions.write_text(json.dumps([[0.0, 0.0]]))
    out = tmp_path / "run"
    result = run_script("scripts/run_stream.py", "--mjcf", str(arm_file), "--ee-link", "tool",
                        "--sim", "mujoco", "--conditions", str(conditions), *SMALL,
                        "--workers", "1", "--out", str(out))  # fmt: skip
    assert result.code == 0, result.err[-2000:]
    assert json.loads((out / "config.json").read_text())["task"]["mjcf"] is True
    assert (out / "arm.urdf").read_text() == mjcf_urdf(str(arm_file))
    evaluated = run_script("scripts/evaluate.py", "--run", str(out), "--positions",
                           str(conditions), "--workers", "1")  # fmt: skip
    assert evaluated.code == 0, evaluated.err[-2000:]


BAD = {
    "not XML": ("<mujoco><worldbody>", "MuJoCo cannot compile it"),
    "a free joint": (
        '<mujoco><worldbody><body name="b"><freejoint/><geom size="0.1"/></body>'
        "</worldbody></mujoco>",
        "body 'b' has a free joint",
    ),
    "two joints in a body": (
        '<mujoco><worldbody><body name="b"><joint name="a"/><joint name="c" axis="0 1 0"/>'
        '<geom size="0.1"/></body></worldbody></mujoco>',
        "body 'b' has 2 joints",
    ),
    "a site named as a body": (
        '<mujoco><worldbody><body name="b"><joint name="a"/><geom size="0.1"/>'
        '<site name="b"/></body></worldbody></mujoco>',
        "site 'b' has a body's name",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_files_that_do_not_convert_are_refused(case: str, tmp_path: Path) -> None:
    text, reason = BAD[case]
    path = tmp_path / "bad.xml"
    path.write_text(text)
    with pytest.raises(LolgpsError, match=reason):
        mjcf_urdf(str(path))


def test_mjcf_refusals_are_one_line(
    arm_file: Path, tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """``--mjcf`` with PyBullet, and a file MuJoCo cannot compile, end with one ``error:`` line
    and exit 2 before any run folder is made."""
    out = str(tmp_path / "run")
    result = run_script("scripts/run_stream.py", "--mjcf", str(arm_file), "--out", out)
    assert (result.code, result.err) == (
        2,
        "error: --mjcf needs --sim mujoco: PyBullet cannot load MJCF\n",
    )
    bad = tmp_path / "bad.xml"
    bad.write_text(BAD["a free joint"][0])
    result = run_script(
        "scripts/run_stream.py", "--mjcf", str(bad), "--sim", "mujoco", "--out", out
    )
    assert result.code == 2
    assert result.err.startswith(f"error: {bad}: body 'b' has a free joint")
    assert result.err.count("\n") == 1
    assert not (tmp_path / "run").exists()
