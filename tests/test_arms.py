"""Any URDF arm: the loader's description, other arms' kinematics, and one-line errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pybullet_data
import pytest
import torch

from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig

DATA = pybullet_data.getDataPath()
XARM = os.path.join(DATA, "xarm/xarm6_robot.urdf")
PANDA = os.path.join(DATA, "franka_panda/panda.urdf")

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


def _inspect(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "scripts/inspect_arm.py", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_inspect_arm_reports_the_kuka() -> None:
    proc = _inspect("--urdf", "robots/kuka_peg.urdf")
    assert proc.returncode == 0, proc.stderr
    assert "iiwa_joint_7" in proc.stdout and "peg_tip" in proc.stdout
    assert "OK" in proc.stdout.splitlines()[-1]


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
        (  # PyBullet's URDF importer segfaults on this one
            lambda tmp: _write(
                tmp,
                "twice.urdf",
                Path("robots/kuka_peg.urdf")
                .read_text()
                .replace('name="iiwa_joint_3"', 'name="iiwa_joint_2"'),
            ),
            "joint name 'iiwa_joint_2' is used twice",
        ),
    ],
)
def test_bad_arms_give_one_error_line(tmp_path: Path, make: object, message: str) -> None:
    assert callable(make)
    proc = _inspect("--urdf", make(tmp_path))
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], proc.stderr


def test_ee_link_not_downstream_of_an_actuated_joint(tmp_path: Path) -> None:
    proc = _inspect("--urdf", "robots/kuka_peg.urdf", "--ee-link", "iiwa_link_0")
    assert proc.returncode == 2 and "not downstream of any actuated joint" in proc.stderr
    proc = _inspect("--urdf", "robots/kuka_peg.urdf", "--ee-link", "nope")
    assert proc.returncode == 2 and "unknown end-effector link" in proc.stderr


def _write(tmp: Path, name: str, text: str) -> str:
    (tmp / name).write_text(text)
    return str(tmp / name)
