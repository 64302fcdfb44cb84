"""Any URDF arm: the loader's description, other arms' kinematics, and one-line errors; the
corpus of published descriptions (``tests/data/arms`` and pybullet_data) loads, agrees with
PyBullet, places the default stream and runs an iteration."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import torch
from conftest import ScriptRun, check_published_arm, finish_script, start_script

from lolgps_torch.arm_probes import REFERENCE_REACH, fit_scale, scaled
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.ik import follow, generic_rank
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.peg import PegConfig
from lolgps_torch.robot.placement import (
    PlacementConfig,
    TaskGeometry,
    place_task,
    vertical_peg_targets,
)
from lolgps_torch.robot.rigid_body import ArmDynamics
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.robot.validate import ArmWarning
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig
from lolgps_torch.task import PegTask, TaskConfig, task_config_from_dict

DATA = pybullet_data.getDataPath()
XARM = os.path.join(DATA, "xarm/xarm6_robot.urdf")
PANDA = os.path.join(DATA, "franka_panda/panda.urdf")
ARMS = Path(__file__).resolve().parent / "data" / "arms"
TROSSEN = ARMS / "trossen_descriptions" / "urdf"
# published descriptions, as published: name -> (URDF, degrees of freedom)
CORPUS = {
    "pybullet-panda": (PANDA, 7),
    "pybullet-xarm6": (XARM, 6),
    "pybullet-kuka-iiwa": (os.path.join(DATA, "kuka_iiwa/model.urdf"), 7),
    "rtb-xarm6": (str(ARMS / "armer_xarm/data/xacro/robots/xarm6/xarm6.urdf"), 6),
    "rtb-vx300s": (str(TROSSEN / "vx300s.urdf"), 6),
    "rtb-wx250s": (str(TROSSEN / "wx250s.urdf"), 6),
    "rtb-wx200": (str(TROSSEN / "wx200.urdf"), 5),
    "rtb-px150": (str(TROSSEN / "px150.urdf"), 5),
}
FETCH = str(ARMS / "mani_skill/fetch/fetch.urdf")
PR2 = str(ARMS / "example-robot-data/robots/pr2_description/urdf/pr2.urdf")
SO100 = str(ARMS / "mani_skill/so100/so100.urdf")
AL5D = ARMS / "lynxmotion_al5d_description/urdf/al5d_robot.urdf"
# published arms on a mobile base, on a torso, and small: name -> (URDF, degrees of freedom,
# the --base-link and --ee-link flags that pick the arm, the scale --scale auto gives it)
MOUNTED: dict[str, tuple[str, int, tuple[str | None, str | None], float]] = {
    "maniskill-fetch": (FETCH, 7, ("torso_lift_link", None), 1.0),
    "erd-pr2-left": (PR2, 7, ("torso_lift_link", "l_wrist_roll_link"), 1.0),
    "maniskill-so100": (SO100, 5, (None, None), 0.552 / REFERENCE_REACH),  # reach 0.552 m
    # 4 joints, reach 0.525 m: the default geometry fits it once the peg points along its hand
    "rtb-al5d": (str(AL5D), 4, (None, None), 1.0),
}
# published descriptions that cannot do the task, and the flag or element their error names
REFUSED = {
    # no <inertial> anywhere: a kinematic-only description
    "rtb-irb140": (ARMS / "abb_irb140_description/urdf/irb140.urdf", "<inertial>"),
}
PAPER_STREAM = tuple(default_training_stream(AreaConfig(), 0)[0])

LINK = '<link name="{n}"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>'
JOINT = (
    '<joint name="{n}" type="{t}"><parent link="{p}"/><child link="{c}"/><origin xyz="0 0 {z}"/>'
    '<axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="10" velocity="2"/></joint>'
)


def _urdf(tmp_path: Path, joint_type: str, length: float) -> str:
    body = "".join(LINK.format(n=f"l{i}") for i in range(3))
    body += JOINT.format(n="j1", t=joint_type, p="l0", c="l1", z=0.05)
    body += JOINT.format(n="j2", t=joint_type, p="l1", c="l2", z=length)
    path = tmp_path / f"{joint_type}_{length}.urdf"
    path.write_text(f'<robot name="toy">{body}</robot>')
    return str(path)


@pytest.mark.parametrize(
    "urdf",
    [
        "robots/kuka_peg.urdf",
        PANDA,
        XARM,
        os.path.join(DATA, "kuka_iiwa/model.urdf"),
    ],
)
def test_real_arms_pass_validation(urdf: str) -> None:
    """Massless fixed links (Panda), principal moments breaking the triangle inequality
    (xArm), massless base and meshes beside the URDF (KUKA model) are all accepted."""
    assert load_arm(urdf).dof >= 6


def test_missing_axis_is_x_in_kinematics_and_simulator(tmp_path: Path) -> None:
    """URDF's default axis is (1, 0, 0); pytorch-kinematics alone would take (0, 0, 1)."""
    path = Path(_urdf(tmp_path, "revolute", 0.3))
    path.write_text(path.read_text().replace('<axis xyz="0 1 0"/>', ""))
    arm = load_arm(str(path))
    kin = PegKinematics(arm)
    world = PegWorld(arm, WorldConfig(), (0.3, 0.0, 0.0))
    qs = np.random.default_rng(0).uniform(-1.5, 1.5, (5, arm.dof))
    expected = []
    for q in qs:
        world.reset(q)
        expected.append(world.points())
    world.close()
    got = kin.points(torch.tensor(qs))
    assert torch.allclose(got, torch.tensor(np.stack(expected)), atol=1e-6, rtol=0)


def test_link_without_inertial_is_massless_in_the_simulator(tmp_path: Path) -> None:
    """URDF reads a missing ``<inertial>`` as zero mass; PyBullet alone would put 1 kg there."""
    text = Path("robots/kuka_peg.urdf").read_text()
    start = text.index('<link name="iiwa_link_ee">')
    inertial = text[start : text.index("</inertial>", start) + len("</inertial>")]
    inertial = inertial[inertial.index("<inertial>") :]
    arm = load_arm(_write(tmp_path, "no_inertial.urdf", text.replace(inertial, "")))
    world = PegWorld(arm, WorldConfig(), (0.6, 0.0, 0.2))
    links = {
        pb.getJointInfo(world.body, i, physicsClientId=world.client)[12].decode(): i
        for i in range(pb.getNumJoints(world.body, physicsClientId=world.client))
    }
    mass = pb.getDynamicsInfo(world.body, links["iiwa_link_ee"], physicsClientId=world.client)[0]
    world.close()
    assert mass == 0.0


def test_panda_description() -> None:
    arm = load_arm(PANDA)
    assert arm.joint_names == tuple(f"panda_joint{i}" for i in range(1, 8))
    assert arm.point_link == "lolgps_peg_tip" and arm.peg_link == "lolgps_peg"  # peg attached
    assert arm.effort[0] == 87.0


INSPECT = "scripts/inspect_arm.py"
ScriptRunner = Callable[..., ScriptRun]


def _inspect(*args: str) -> subprocess.CompletedProcess[str]:
    """inspect_arm.py in a process of its own, as one runs it (the other tests run it in the
    test's process: ``run_script``)."""
    return subprocess.run(
        [sys.executable, INSPECT, *args], capture_output=True, text=True, timeout=300
    )


def test_inspect_arm_reports_the_kuka() -> None:
    proc = _inspect("--urdf", "robots/kuka_peg.urdf")
    assert proc.returncode == 0, proc.stderr
    assert "iiwa_joint_7" in proc.stdout and "peg_tip" in proc.stdout
    assert "OK" in proc.stdout.splitlines()[-1]


def test_an_arm_pybullet_would_crash_on_is_one_error_line_from_the_script(tmp_path: Path) -> None:
    """PyBullet's URDF importer segfaults on a joint name used twice: the loader refuses it
    first, and the script exits with status 2 and one line (in a forked process: a segfault
    there would fail this test, not the test process)."""
    text = Path("robots/kuka_peg.urdf").read_text()
    urdf = _write(
        tmp_path, "twice.urdf", text.replace('name="iiwa_joint_3"', 'name="iiwa_joint_2"')
    )
    log = tmp_path / "inspect.log"
    code = finish_script(start_script([sys.executable, INSPECT, "--urdf", urdf], log), log)
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, log.read_text()
    assert lines[0].startswith("error: ") and "joint name 'iiwa_joint_2' is used twice" in lines[0]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda tmp: str(tmp / "missing.urdf"), "not found"),
        (
            lambda tmp: _write(tmp, "bad.urdf", "<robot name='x'><link name='a'></robot>"),
            "malformed XML",
        ),
        (lambda tmp: _urdf(tmp, "fixed", 0.3), "no revolute or continuous joints"),
        (
            lambda tmp: _write(
                tmp,
                "ent.urdf",
                '<!DOCTYPE r [<!ENTITY e SYSTEM "file:///etc/passwd">]><robot name="r">&e;</robot>',
            ),
            "entities",
        ),
        (lambda tmp: _urdf(tmp, "revolute", 0.02), "too short"),
    ],
)
def test_bad_arms_give_one_error_line(
    tmp_path: Path, make: object, message: str, run_script: ScriptRunner
) -> None:
    assert callable(make)
    result = run_script(INSPECT, "--urdf", make(tmp_path))
    assert result.code == 2
    lines = [line for line in result.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], result.err


def test_ee_link_not_downstream_of_an_actuated_joint(run_script: ScriptRunner) -> None:
    result = run_script(INSPECT, "--urdf", "robots/kuka_peg.urdf", "--ee-link", "iiwa_link_0")
    assert result.code == 2 and "not downstream of any actuated joint" in result.err
    result = run_script(INSPECT, "--urdf", "robots/kuka_peg.urdf", "--ee-link", "nope")
    assert result.code == 2 and "unknown end-effector link" in result.err


def _write(tmp: Path, name: str, text: str) -> str:
    (tmp / name).write_text(text)
    return str(tmp / name)


def _slow(names: list[str], slow: set[str]) -> list[object]:
    """``names`` as parameters, those in ``slow`` marked slow (the longest of a kind that the
    others cover in the default suite)."""
    return [pytest.param(n, marks=pytest.mark.slow) if n in slow else n for n in names]


@pytest.mark.parametrize(
    "name",
    _slow(
        sorted(CORPUS),
        {"rtb-px150", "rtb-wx250s", "rtb-vx300s", "pybullet-kuka-iiwa", "pybullet-xarm6"},
    ),
)
def test_published_arm_loads_places_the_stream_and_iterates(name: str) -> None:
    """Loaded as published (``package://`` meshes absent: warned, not refused), the kinematics
    agree with PyBullet, the hole is placed so that the whole default stream is reachable, and
    one iteration of the trajectory-centric loop runs (a short episode)."""
    urdf, dof = CORPUS[name]
    check_published_arm(urdf, dof)


@pytest.mark.parametrize("name", _slow(sorted(MOUNTED), {"maniskill-so100"}))
def test_arm_on_a_base_or_torso_or_small_loads_places_and_iterates(name: str) -> None:
    """As the published arms above, with the arm picked by --base-link/--ee-link, the joints
    above and off it held, and the stream scaled to a small arm's reach."""
    urdf, dof, chain, scale = MOUNTED[name]
    check_published_arm(urdf, dof, chain=chain, scale=scale)


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_published_arm_that_cannot_do_the_task_gets_one_error_line(
    name: str, tmp_path: Path, run_script: ScriptRunner
) -> None:
    """The default stream, unscaled, stops before any work with one line naming what to
    change.  (The small arms once refused here, rtb-data's PincherX 100 and AL5D, are placed
    now: the AL5D's peg along its hand, the PincherX unscaled from the spots about its sampled
    tips; ``--scale auto`` still scales the PincherX, its grid fitting there first.)"""
    urdf, message = REFUSED[name]
    result = run_script(
        "scripts/run_stream.py", "--urdf", str(urdf), "--scale", "1", "--out", str(tmp_path)
    )
    errors = [line for line in result.err.splitlines() if line.startswith("error:")]
    assert result.code == 2 and len(errors) == 1 and message in errors[0], result.err
    assert not list(tmp_path.iterdir())


def test_missing_meshes_are_one_warning_line_and_the_arm_loads(run_script: ScriptRunner) -> None:
    result = run_script(INSPECT, "--urdf", CORPUS["rtb-vx300s"][0], "--checks", "1")
    assert result.code == 0, result.err
    warned = [line for line in result.err.splitlines() if line.startswith("warning:")]
    assert len(warned) == 1 and "package://trossen_descriptions/meshes/" in warned[0]
    assert "OK" in result.out.splitlines()[-1]


def _package_with_mesh(root: Path, package: str, manifest: bool) -> Path:
    """``root/<folder>/urdf/arm.urdf`` naming ``package://<package>/meshes/base.obj``, with the
    mesh in the package; the folder is named ``package``, or holds a package.xml naming it."""
    folder = root / ("pkg_folder" if manifest else package)
    (folder / "urdf").mkdir(parents=True)
    (folder / "meshes").mkdir()
    (folder / "meshes" / "base.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    if manifest:
        (folder / "package.xml").write_text(f"<package><name>{package}</name></package>")
    text = Path("robots/kuka_peg.urdf").read_text()
    shape = '<geometry><cylinder radius="0.07" length="0.1575"/></geometry>'
    mesh = f'<geometry><mesh filename="package://{package}/meshes/base.obj"/></geometry>'
    (folder / "urdf" / "arm.urdf").write_text(text.replace(shape, mesh, 1))
    return folder


@pytest.mark.parametrize("manifest", [False, True])
def test_package_uri_is_found_among_the_urdf_ancestors(tmp_path: Path, manifest: bool) -> None:
    folder = _package_with_mesh(tmp_path, "my_arm_description", manifest)
    arm = load_arm(str(folder / "urdf" / "arm.urdf"))
    assert f'filename="{folder / "meshes" / "base.obj"}"' in arm.urdf_text


@pytest.mark.parametrize("how", ["ROS_PACKAGE_PATH", "package_path"])
def test_package_uri_is_found_on_the_package_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str
) -> None:
    """The URDF copied away from its package finds it through ROS_PACKAGE_PATH or
    ``--package-path`` (a folder holding the package, searched below)."""
    folder = _package_with_mesh(tmp_path / "src" / "group", "my_arm_description", True)
    away = tmp_path / "elsewhere"
    away.mkdir()
    shutil.copy(folder / "urdf" / "arm.urdf", away / "arm.urdf")
    with pytest.warns(ArmWarning, match="mesh file"):  # and the shape is dropped
        assert "base.obj" not in load_arm(str(away / "arm.urdf")).urdf_text
    if how == "ROS_PACKAGE_PATH":
        monkeypatch.setenv("ROS_PACKAGE_PATH", str(tmp_path / "src"))
        arm = load_arm(str(away / "arm.urdf"))
    else:
        arm = load_arm(str(away / "arm.urdf"), package_path=(str(tmp_path / "src"),))
    assert f'filename="{folder / "meshes" / "base.obj"}"' in arm.urdf_text


def test_package_path_flag_reaches_the_loader(tmp_path: Path, run_script: ScriptRunner) -> None:
    folder = _package_with_mesh(tmp_path / "src", "my_arm_description", True)
    away = str(tmp_path / "arm.urdf")
    shutil.copy(folder / "urdf" / "arm.urdf", away)
    result = run_script(
        INSPECT, "--urdf", away, "--checks", "1", "--package-path", str(tmp_path / "src")
    )
    assert result.code == 0 and "warning:" not in result.err, result.err
    result = run_script(INSPECT, "--urdf", away, "--package-path", str(tmp_path / "nowhere"))
    assert result.code == 2 and "--package-path" in result.err.splitlines()[-1]


def _kuka_variant(tmp_path: Path, old: str, new: str) -> str:
    text = Path("robots/kuka_peg.urdf").read_text()
    assert old in text
    return _write(tmp_path, "variant.urdf", text.replace(old, new, 1))


def test_thin_link_with_a_zero_principal_moment_loads_and_simulates(tmp_path: Path) -> None:
    """A thin rod's inertia, diag(I, I, 0), is physical: positive semi-definite."""
    text = Path("robots/kuka_peg.urdf").read_text()
    link7 = text.index('<link name="iiwa_link_7">')
    izz = text.index("izz=", link7)
    end = text.index('"', izz + 5)
    path = _write(tmp_path, "thin.urdf", text[:izz] + 'izz="0' + text[end:])
    task = PegTask(TaskConfig(urdf=path, world=WorldConfig(T=10)), n_worlds=1)
    try:
        hold = lambda t, x, rows: torch.zeros(x.shape[0], task.arm.dof, dtype=torch.float64)  # noqa: E731
        assert torch.isfinite(task.sample(hold, [(0.0, 0.0)]).x).all()
    finally:
        task.close()


def test_an_inertia_negative_only_by_rounding_loads(tmp_path: Path) -> None:
    """iCub's published head: all zero but ``ixz = 2.4e-35`` (principal moments +-2.4e-35),
    which is zero; a matrix negative beyond rounding is still refused."""
    text = Path("robots/kuka_peg.urdf").read_text()
    link7 = text.index('<link name="iiwa_link_7">')
    start = text.index("<inertia ", link7)
    end = text.index("/>", start) + 2
    zero = '<inertia ixx="0" ixy="0" ixz="2.40741e-35" iyy="0" iyz="0" izz="0"/>'
    load_arm(_write(tmp_path, "rounding.urdf", text[:start] + zero + text[end:]))
    negative = zero.replace("2.40741e-35", "1e-6")
    with pytest.raises(LolgpsError, match="not positive semi-definite"):
        load_arm(_write(tmp_path, "negative.urdf", text[:start] + negative + text[end:]))


def test_fixed_joint_limits_are_ignored(tmp_path: Path) -> None:
    """Published fixed mounting joints carry placeholder limits such as effort 0."""
    path = _kuka_variant(
        tmp_path,
        '<joint name="iiwa_joint_ee" type="fixed">',
        '<joint name="iiwa_joint_ee" type="fixed"><limit effort="0" velocity="0"/>',
    )
    assert load_arm(path).dof == 7


def test_off_chain_and_mimic_joints_are_locked_at_their_limit(tmp_path: Path) -> None:
    """A finger (prismatic, limits [0.01, 0.04]) and its mimic twin on the last link: neither
    is actuated; both become fixed at the middle of their limits (0 is outside them), 0.025,
    folded into their origins."""
    finger = (
        '<link name="f{i}"><inertial><mass value="0.01"/><inertia ixx="1e-6" iyy="1e-6" '
        'izz="1e-6" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        '<joint name="finger_{i}" type="prismatic"><parent link="iiwa_link_7"/>'
        '<child link="f{i}"/><origin xyz="0 0 0.05"/><axis xyz="0 1 0"/>{mimic}'
        '<limit lower="0.01" upper="0.04" effort="0" velocity="0.2"/></joint>'
    )
    extra = finger.format(i=1, mimic="") + finger.format(i=2, mimic='<mimic joint="finger_1"/>')
    text = Path("robots/kuka_peg.urdf").read_text().replace("</robot>", extra + "</robot>")
    arm = load_arm(_write(tmp_path, "fingers.urdf", text))
    assert len(arm.joint_names) == 7 and "finger_1" not in arm.joint_names
    joints = {j.get("name"): j for j in ET.fromstring(arm.urdf_text).findall("joint")}
    for name in ("finger_1", "finger_2"):
        origin = joints[name].find("origin")
        assert joints[name].get("type") == "fixed" and origin is not None
        assert np.allclose([float(v) for v in origin.get("xyz", "").split()], [0, 0.025, 0.05])
    assert arm.held == (("finger_1", 0.025), ("finger_2", 0.025))


def test_a_published_arm_with_a_gripper_ends_before_the_gripper() -> None:
    """pybullet_data's Panda: the fingers are locked and the end effector is the hand's TCP."""
    arm = load_arm(PANDA)
    assert arm.ee_link == "panda_grasptarget" and arm.peg_axis == "z"
    assert not any("finger" in name for name in arm.joint_names)


def test_automatic_peg_axis_points_away_from_the_last_joint() -> None:
    """The Trossen wrist frame's +x runs out along the gripper."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        assert load_arm(CORPUS["rtb-wx250s"][0]).peg_axis == "x"


def test_two_equal_arms_need_an_end_effector(tmp_path: Path) -> None:
    body = LINK.format(n="base")
    for side in "ab":
        body += "".join(LINK.format(n=f"{side}{i}") for i in (1, 2))
        body += JOINT.format(n=f"{side}j1", t="revolute", p="base", c=f"{side}1", z=0.1)
        body += JOINT.format(n=f"{side}j2", t="revolute", p=f"{side}1", c=f"{side}2", z=0.3)
    path = _write(tmp_path, "two.urdf", f'<robot name="two">{body}</robot>')
    with pytest.raises(
        LolgpsError,
        match="2 arms below link 'base', ending at a2, b2: pick one with --base-link base "
        "--ee-link a2 or --base-link base --ee-link b2",
    ):
        load_arm(path)
    assert load_arm(path, ee_link="b2").joint_names == ("bj1", "bj2")


@pytest.mark.parametrize(
    ("make", "flag"),
    [
        (lambda: PegConfig(axis="w"), "--peg-axis"),  # type: ignore[arg-type]
        (lambda: PegConfig(length=0.0), "--peg-length"),
        (lambda: PegConfig(radius=float("nan")), "--peg-radius"),
        (lambda: WorldConfig(friction=-1.0), "--friction"),
        (lambda: WorldConfig(dt=0.0), "dt"),
        (lambda: WorldConfig(clearance_bottom=0.01), "clearance"),
        (lambda: PlacementConfig(q0=(float("inf"),)), "--q0"),
        (lambda: PlacementConfig(positions=((0.0, float("nan")),)), "positions"),
        (lambda: TaskConfig(urdf="x", package_path=("/nonexistent/folder",)), "--package-path"),
    ],
)
def test_task_configs_check_their_fields(make: object, flag: str) -> None:
    assert callable(make)
    with pytest.raises(LolgpsError, match=flag):
        make()


@pytest.mark.long
@pytest.mark.parametrize("name", sorted(CORPUS) + sorted(MOUNTED))
def test_published_arm_learns_the_default_stream(name: str, tmp_path: Path) -> None:
    """The main job with only ``--urdf`` (and the flags that pick an arm on a base or torso):
    the global policy succeeds at >= 7 of the 8 training positions and every local controller
    ends within the success threshold. Minutes each (an hour in all): marked long."""
    out = tmp_path / "run"
    urdf, _, (base, ee), _ = (
        MOUNTED[name] if name in MOUNTED else (CORPUS[name][0], 0, (None, None), 1)
    )
    picks = [*(["--base-link", base] if base else []), *(["--ee-link", ee] if ee else [])]
    cmd = [sys.executable, "scripts/run_stream.py", "--urdf", urdf, *picks, "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    entries = json.loads((out / "summary.json").read_text())["conditions"]
    assert len(entries) == 8
    assert max(e["local_final_distance"] for e in entries) <= WorldConfig().success_threshold
    assert sum(bool(e["policy_success_end"]) for e in entries) >= 7


def test_a_continuous_joint_needs_no_limit_and_a_mobile_base_is_part_of_the_chain() -> None:
    """ManiSkill's Fetch: the base's rotation is a continuous joint without <limit> (as ROS
    allows); from the root it is the arm's first joint, its effort derived; the base's
    prismatic joints are held."""
    with pytest.warns(ArmWarning, match="root_z_rotation_joint"):
        arm = load_arm(FETCH)
    assert arm.joint_names[0] == "root_z_rotation_joint" and arm.dof == 8
    assert arm.effort[0] > 0 and arm.base_link == "root"
    assert ("root_x_axis_joint", 0.0) in arm.held


def test_base_link_holds_the_joints_above_and_off_the_chain() -> None:
    """--base-link torso_lift_link: the arm's 7 joints; the base, torso, head and fingers held,
    each where --hold says or at 0; the torso lift's height is folded into its origin."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        low = load_arm(FETCH, base_link="torso_lift_link")
        high = load_arm(FETCH, base_link="torso_lift_link", hold={"torso_lift_joint": 0.3})
    assert low.joint_names[0] == "shoulder_pan_joint" and low.dof == 7
    held = dict(high.held)
    assert held["torso_lift_joint"] == 0.3 and held["head_pan_joint"] == 0.0
    assert {"root_z_rotation_joint", "l_gripper_finger_joint"} <= set(held)
    lifts = [
        next(j for j in ET.fromstring(a.urdf_text).findall("joint") if j.get("name") == name)
        for a, name in ((low, "torso_lift_joint"), (high, "torso_lift_joint"))
    ]
    heights = [float(j.find("origin").get("xyz").split()[2]) for j in lifts]  # type: ignore[union-attr]
    assert heights[1] - heights[0] == pytest.approx(0.3)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"base_link": "nope"}, "unknown base link 'nope'"),
        (
            {"base_link": "head_pan_link", "ee_link": "wrist_roll_link"},
            "base link .head_pan_link. is not on the chain",
        ),
        ({"hold": {"shoulder_pan_joint": 0.1}}, "--hold shoulder_pan_joint=0.1: not a joint"),
        ({"hold": {"nope": 0.1}}, "--hold nope=0.1: not a joint that is held"),
        ({"hold": {"torso_lift_joint": 1.0}}, "outside the joint's limits"),
    ],
)
def test_bad_base_link_or_hold_is_one_error(kwargs: dict, message: str) -> None:
    with warnings.catch_warnings(), pytest.raises(LolgpsError, match=message):
        warnings.simplefilter("ignore", ArmWarning)
        load_arm(FETCH, **{"base_link": "torso_lift_link", **kwargs})


def test_several_arms_name_the_flags_that_pick_one() -> None:
    with pytest.raises(LolgpsError, match="--base-link torso_lift_link --ee-link l_wrist_roll"):
        load_arm(PR2)


def test_a_limit_without_velocity_says_what_to_add(tmp_path: Path) -> None:
    path = _kuka_variant(tmp_path, ' velocity="1.4835298641951802"', "")
    with pytest.raises(LolgpsError, match='has no velocity attribute .* add velocity="..."'):
        load_arm(path)


def test_task_config_records_the_arm_picked_and_the_scale() -> None:
    """config.json's task (``asdict``) reads back with the base link, the held joints and the
    scale, so that evaluate.py and render.py rebuild the same arm and test areas."""
    config = TaskConfig(urdf="x", base_link="b", hold=("j=0.5",), scale=0.5)
    assert task_config_from_dict(dataclasses.asdict(config)) == config
    assert config.held() == {"j": 0.5}
    for bad in (("j",), ("j=x",), ("j=1", "j=2"), ("=1",)):
        with pytest.raises(LolgpsError, match="--hold"):
            TaskConfig(urdf="x", hold=bad)
    with pytest.raises(LolgpsError, match="--scale"):
        TaskConfig(urdf="x", scale=0.0)


def test_scaled_geometry_and_an_arm_that_fits_is_left_as_it_is() -> None:
    """``scaled`` shrinks the positions, the start offset and the attached peg; the KUKA fits
    the default stream, so ``fit_scale`` leaves it at scale 1 and says nothing."""
    base = TaskConfig(
        urdf="robots/kuka_peg.urdf", placement=PlacementConfig(positions=PAPER_STREAM)
    )
    half = scaled(base, 0.5)
    assert half.scale == 0.5 and half.peg.length == pytest.approx(0.1)
    assert half.placement.positions[0] == pytest.approx((-0.01, -0.01))
    assert half.placement.start_offset == pytest.approx((-0.05, 0.0, 0.1))
    placed, note = fit_scale(base)
    assert note == "" and placed.scale == 1.0 and placed.placement.mouth is not None


def test_inspect_lists_held_joints_and_pybullet_stays_quiet(run_script: ScriptRunner) -> None:
    """The held joints are listed; PyBullet's own warnings (Fetch's fingers' inertia) do not
    reach the terminal, only the loader's one line."""
    result = run_script(
        INSPECT, "--urdf", FETCH, "--base-link", "torso_lift_link", "--hold", "torso_lift_joint=0.2"
    )
    assert result.code == 0, result.err
    assert "torso_lift_joint" in result.out and "base link     torso_lift_link" in result.out
    assert "b3Warning" not in result.out + result.err


@pytest.mark.parametrize(
    "flags",
    [("--base-link", "nope"), ("--hold", "x"), ("--hold", "x=1"), ("--scale", "big")],
)
def test_bad_arm_flags_are_one_error_line_before_any_work(
    flags: tuple[str, ...], tmp_path: Path, run_script: ScriptRunner
) -> None:
    result = run_script("scripts/run_stream.py", *flags, "--out", str(tmp_path / "run"))
    errors = [line for line in result.err.splitlines() if line.startswith("error:")]
    assert result.code == 2 and len(errors) == 1, result.err
    assert not (tmp_path / "run").exists()


def _hanging_arm(tmp_path: Path, seed: int) -> str:
    """A 5-joint arm hanging from a torso beside it (yaw, abduction, then three pitch joints
    straight down), its link lengths drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    upper, fore, hand = rng.uniform(0.25, 0.4), rng.uniform(0.25, 0.4), rng.uniform(0.05, 0.1)
    joints = [  # (axis, origin from the parent link)
        ("0 0 1", f"0 {rng.uniform(0.1, 0.3):.3f} 0"),
        ("1 0 0", "0 0 -0.05"),
        ("0 1 0", "0 0 -0.05"),
        ("0 1 0", f"0 0 {-upper:.3f}"),
        ("0 1 0", f"0 0 {-fore:.3f}"),
    ]
    body = "".join(LINK.format(n=f"l{i}") for i in range(7))
    for i, (axis, xyz) in enumerate(joints, 1):
        body += (
            f'<joint name="j{i}" type="revolute"><parent link="l{i - 1}"/><child link="l{i}"/>'
            f'<origin xyz="{xyz}"/><axis xyz="{axis}"/>'
            '<limit lower="-2" upper="2" effort="40" velocity="2"/></joint>'
        )
    body += f'<joint name="hand" type="fixed"><parent link="l5"/><child link="l6"/><origin xyz="0 0 {-hand:.3f}"/></joint>'
    path = tmp_path / f"hanging_{seed}.urdf"
    path.write_text(f'<robot name="hanging">{body}</robot>')
    return str(path)


def _assert_placed(
    arm: ArmSpec, kin: PegKinematics, config: PlacementConfig, depth: float, geometry: TaskGeometry
) -> None:
    """The start pose points the peg straight down above the mouth, and every floor of the
    stream is reached from it continuously (``follow``) within the IK tolerance."""
    start = torch.tensor(geometry.q0, dtype=torch.float64)
    tip, top = kin.points(start[None])[0]
    mouth = torch.tensor(geometry.nominal_mouth, dtype=torch.float64)
    assert float((top - tip)[:2].norm()) <= 2 * config.ik_tolerance
    assert float(tip[2]) > float(mouth[2])
    floors = mouth + torch.nn.functional.pad(
        torch.tensor(config.positions, dtype=torch.float64), (0, 1), value=-depth
    )
    holes = vertical_peg_targets(floors, -arm.point_offsets[1][2])
    rank = generic_rank(kin, start + 0.1 * torch.randn(8, arm.dof, dtype=torch.float64))
    error, _ = follow(kin, arm, start, holes, rank)
    assert float(error.max()) <= config.ik_tolerance


@pytest.mark.parametrize("seed", [0, 1])
def test_the_spots_about_the_sampled_tips_place_a_hanging_arm(seed: int, tmp_path: Path) -> None:
    """An arm hanging from a torso (link lengths fuzzed), placed from the spots about its
    sampled down-pointing tips alone: the start and the whole default stream are reached."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        arm = load_arm(_hanging_arm(tmp_path, seed))
    kin = PegKinematics(arm)
    config = PlacementConfig(positions=PAPER_STREAM)
    geometry = place_task(arm, kin, config, WorldConfig().depth, spots="sampled")
    _assert_placed(arm, kin, config, WorldConfig().depth, geometry)


def test_a_published_small_arm_is_placed_from_the_sampled_spots_too() -> None:
    """rtb-data's Lynxmotion AL5D (4 joints; the peg along its last link, square to its
    pitching wrist) places the default stream from the spots about its sampled tips alone (its
    grid places it too: ``MOUNTED``); an unknown set of spots is one error."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        arm = load_arm(str(AL5D))
    kin = PegKinematics(arm)
    config = PlacementConfig(positions=PAPER_STREAM)
    geometry = place_task(arm, kin, config, WorldConfig().depth, spots="sampled")
    _assert_placed(arm, kin, config, WorldConfig().depth, geometry)
    with pytest.raises(LolgpsError, match="spots"):
        place_task(arm, kin, config, WorldConfig().depth, spots="all")  # type: ignore[arg-type]


def test_a_body_too_large_for_pybullets_link_states_merges_links_off_the_arm(
    tmp_path: Path,
) -> None:
    """PyBullet keeps link states for bodies of up to 128 links (example-robot-data's
    two-armed TIAGo has 131): the KUKA with 130 fixed links added off its chain (on its base
    and its last link, offset and turned) loads with one warning, its extra links merged into
    their parents, and builds; its mass matrix is PyBullet's for the whole unmerged body (an
    independent answer: its own parser, every link kept), to rounding."""
    robots = Path("robots").resolve()
    text = (robots / "kuka_peg.urdf").read_text().replace('filename="', f'filename="{robots}/')
    extra = "\n".join(
        f'<link name="extra{i}"><inertial><origin xyz="0.01 {0.001 * i} 0" rpy="0.3 0 0.2"/>'
        f'<mass value="{0.01 + 0.001 * i}"/><inertia ixx="1e-5" iyy="2e-5" izz="1.5e-5" '
        f'ixy="1e-6" ixz="0" iyz="0"/></inertial></link>'
        f'<joint name="extra{i}_joint" type="fixed"><parent link="'
        f'{"iiwa_link_0" if i % 2 else "iiwa_link_7"}"/><child link="extra{i}"/>'
        f'<origin xyz="0.05 0.02 {0.01 * (i % 7)}" rpy="0.1 {0.01 * i} 0.5"/></joint>'
        for i in range(130)
    )
    path = _write(tmp_path, "extra130.urdf", text.replace("</robot>", extra + "</robot>"))
    with pytest.warns(ArmWarning, match="merged into their parents"):
        arm = load_arm(path)
    PegWorld(arm, WorldConfig(), (0.6, 0.0, 0.2)).close()
    assert arm.urdf_text.count("<link ") <= 128
    client = pb.connect(pb.DIRECT)
    try:
        body = pb.loadURDF(path, useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE,
                           physicsClientId=client)  # fmt: skip
        q = [0.3, -0.5, 0.7, 1.1, -0.4, 0.9, 0.2]
        expected = np.asarray(pb.calculateMassMatrix(body, q, physicsClientId=client))
    finally:
        pb.disconnect(client)
    found = ArmDynamics(arm, inertia="pybullet").mass_matrix(torch.tensor(q, dtype=torch.float64))
    np.testing.assert_allclose(found.numpy(), expected, rtol=1e-9, atol=1e-12)
