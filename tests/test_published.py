"""More published arm descriptions, as published (``tests/data/arms`` from airo-models,
robot_properties_fingers and rtb-data; pybullet_data's other arms): each loads, agrees with
PyBullet, places the default stream and runs an iteration, or stops with one error line
naming what to change; and the loader's handling of what they carry (other tools' undeclared
XML prefixes, unnamed visual materials, meshes PyBullet cannot read, robot fingers whose
every joint is named ``finger_...``, tool frames beside gripper bases, torque limits given as
0), fuzzed; the simulated arm without its visual shapes."""

from __future__ import annotations

import random
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import pybullet_data
import pytest
import torch
from conftest import ScriptRun, check_published_arm, fk_gap

from lolgps_torch.data.run_folder import portable_urdf
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig, default_training_stream
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.effort import derived_effort
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.robot.validate import ArmWarning
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.world import PegWorld, WorldConfig
from lolgps_torch.task import PegTask, TaskConfig

DATA = pybullet_data.getDataPath()
ARMS = Path(__file__).resolve().parent / "data" / "arms"
TROSSEN = ARMS / "trossen_descriptions" / "urdf"
UR5E = ARMS / "airo_models/arms/ur5e/ur5e.urdf"
KR16 = ARMS / "kuka_description/kuka_kr16/urdf/kr16_2.urdf"
# published descriptions, as published: name -> (URDF, degrees of freedom, end effector found)
PUBLISHED = {
    "airo-ur3e": (ARMS / "airo_models/arms/ur3e/ur3e.urdf", 6, "tool0"),
    "airo-ur5e": (UR5E, 6, "tool0"),
    "rtb-rx200": (TROSSEN / "rx200.urdf", 5, "/ee_arm_link"),
    "rtb-vx300": (TROSSEN / "vx300.urdf", 5, "/ee_arm_link"),
    "pybullet-xarm6-gripper": (Path(DATA, "xarm/xarm6_with_gripper.urdf"), 6, "link6"),
    "pybullet-iiwa-vr-limits": (Path(DATA, "kuka_iiwa/model_vr_limits.urdf"), 7, "lbr_iiwa_link_7"),
    # ROS-Industrial: effort="0" on every joint, derived from the arm
    "rtb-kr16": (KR16, 6, "tool0"),
    "rtb-kr120": (ARMS / "kuka_description/kuka_kr120/urdf/kr120r2500pro.urdf", 6, "tool0"),
}
KR6 = ARMS / "kuka_description/kuka_kr6/urdf/kr6r700sixx.urdf"
# published descriptions that cannot do the task as published: what their one error line says
REFUSED = {
    "rtb-kr6": (  # no <inertial> at all; its visuals' materials are named "": not what refuses it
        KR6,
        "a kinematic-only description",
    ),
    "airo-robotiq-2f85": (  # a gripper alone
        ARMS / "airo_models/grippers/robotiq_2f_85/urdf/robotiq_2f_85.urdf",
        "the peg cannot point down",
    ),
    "fingers-finger": (  # 3 joints: the peg points down along a curve at most
        ARMS / "robot_properties_fingers/urdf/finger.urdf",
        "the start pose do not fit in the reach of this arm",
    ),
    "fingers-trifinger": (
        ARMS / "robot_properties_fingers/urdf/trifinger.urdf",
        "3 arms below link 'upper_holder_link', ending at finger_tip_link_0, "
        "finger_tip_link_120, finger_tip_link_240: pick one with --base-link upper_holder_link "
        "--ee-link finger_tip_link_0",
    ),
}
PAPER_STREAM = tuple(default_training_stream(AreaConfig(), 0)[0])
LINK = (
    '<link name="{n}"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" '
    'ixy="0" ixz="0" iyz="0"/></inertial>{extra}</link>'
)
JOINT = (
    '<joint name="{n}" type="{t}"><parent link="{p}"/><child link="{c}"/><origin xyz="{xyz}"/>'
    '<axis xyz="{axis}"/><limit lower="-2" upper="2" effort="10" velocity="2"/></joint>'
)


ScriptRunner = Callable[..., ScriptRun]


def _one_error_line(run_script: ScriptRunner, urdf: Path) -> str:
    """``inspect_arm.py``'s one ``error:`` line on ``urdf`` (exit 2, no traceback)."""
    proc = run_script("scripts/inspect_arm.py", "--urdf", str(urdf), "--checks", "1")
    errors = [line for line in proc.err.splitlines() if line.startswith("error:")]
    assert proc.code == 2 and len(errors) == 1, proc.err
    assert "Traceback" not in proc.err
    return errors[0]


SLOW_PUBLISHED = {"rtb-rx200", "rtb-vx300", "airo-ur3e", "rtb-kr16", "pybullet-iiwa-vr-limits"}


def _load_quietly(path: str | Path, ee_link: str | None = None) -> tuple[ArmSpec, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ArmWarning)
        arm = load_arm(str(path), ee_link)
    return arm, [str(w.message) for w in caught if issubclass(w.category, ArmWarning)]


@pytest.mark.parametrize(
    "name",
    [  # slow: the 5-DoF Trossen arms (test_arms' WX200 runs by default), and one of each pair
        pytest.param(n, marks=pytest.mark.slow) if n in SLOW_PUBLISHED else n
        for n in sorted(PUBLISHED)
    ],
)
def test_published_arm_loads_places_the_stream_and_iterates(name: str) -> None:
    """As published, the end effector is found, the kinematics agree with PyBullet, the whole
    default stream is reachable from the placed hole, and one short iteration runs."""
    urdf, dof, ee_link = PUBLISHED[name]
    check_published_arm(str(urdf), dof, ee_link)


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_published_description_that_cannot_do_the_task_gets_one_error_line(
    name: str, run_script: ScriptRunner
) -> None:
    urdf, message = REFUSED[name]
    assert message in _one_error_line(run_script, urdf)


def test_a_start_pose_only_a_little_above_the_hole_is_found() -> None:
    """rtb-data's RX 150 points the peg down over the hole only up to a little above it (it was
    refused: "not the start 0.20 m (or half that) above the hole"): the placement's further
    spots try the start a quarter as high, and it is placed."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        task = PegTask(TaskConfig(urdf=str(TROSSEN / "rx150.urdf")), n_worlds=1)
    try:
        tip = task.kinematics.points(task.q0)[0]
        assert 0.0 < float(tip[2]) - task.geometry.nominal_mouth[2] <= 0.2 + 1e-6
    finally:
        task.close()


def test_undeclared_prefixes_are_declared_and_their_extensions_dropped() -> None:
    """airo-models' UR5e carries ``drake:acceleration`` on its limits, undeclared."""
    assert "xmlns:drake" not in UR5E.read_text() and "drake:acceleration" in UR5E.read_text()
    arm, _ = _load_quietly(UR5E)
    assert "drake" not in arm.urdf_text
    assert len(arm.joint_names) == 6


def _toy(tmp_path: Path, body: str, name: str = "toy.urdf") -> Path:
    path = tmp_path / name
    path.write_text(f'<robot name="toy">{body}</robot>')
    return path


def _chain(names: tuple[str, ...], extra: str = "") -> str:
    """A vertical base with links l1.. on revolute joints ``names`` (0.3 m apart, y axes)."""
    body = LINK.format(n="base", extra="")
    parent = "base"
    for i, joint in enumerate(names, 1):
        body += LINK.format(n=f"l{i}", extra=extra if i == len(names) else "")
        axis = "0 0 1" if i == 1 else "0 1 0"
        xyz = "0 0 0.1" if i == 1 else "0 0 0.3"
        body += JOINT.format(n=joint, t="revolute", p=parent, c=f"l{i}", xyz=xyz, axis=axis)
        parent = f"l{i}"
    return body


def test_unnamed_visual_materials_are_named(tmp_path: Path) -> None:
    visual = (
        '<visual><geometry><box size="0.05 0.05 0.05"/></geometry>'
        '<material name=""><color rgba="1 0 0 1"/></material></visual>'
    )
    arm, _ = _load_quietly(_toy(tmp_path, _chain(("j1", "j2", "j3"), visual)))
    names = [m.get("name") for m in ET.fromstring(arm.urdf_text).iter("material")]
    assert names and all(names)
    top = f'<material name=""><color rgba="1 0 0 1"/></material>{_chain(("j1", "j2"))}'
    nameless = _chain(("j1", "j2"), visual.replace(' name=""', ""))
    for i, body in enumerate((top, nameless)):  # as ROS's parser, which accepts name=""
        with pytest.raises(LolgpsError, match="<material> has no name"):
            load_arm(str(_toy(tmp_path, body, f"bad{i}.urdf")))


def test_a_hands_driving_joint_ends_the_arm_whatever_its_name(tmp_path: Path) -> None:
    """As Romeo's hand: a joint named ``LHand`` drives one finger, and three sibling joints
    mimic it; the arm ends at the wrist link they hang from, not at that finger."""
    body = _chain(("j1", "j2", "j3"))
    for name in ("f1", "f2", "f3", "f4"):
        body += LINK.format(n=name, extra="")
    body += JOINT.format(n="LHand", t="revolute", p="l3", c="f1", xyz="0.05 0 0", axis="0 1 0")
    for i, name in enumerate(("f2", "f3", "f4"), 2):
        body += JOINT.format(
            n=f"follower{i}", t="revolute", p="l3", c=name, xyz="0.05 0 0", axis="0 1 0"
        ).replace("</joint>", '<mimic joint="LHand"/></joint>')
    arm, _ = _load_quietly(_toy(tmp_path, body))
    assert arm.ee_link == "l3" and arm.dof == 3


def test_a_texture_without_a_file_is_accepted_and_dropped(tmp_path: Path) -> None:
    """iCub's published visuals hold ``<texture />``, which ROS's parser accepts."""
    visual = (
        '<visual><geometry><box size="0.05 0.05 0.05"/></geometry>'
        '<material name="m"><color rgba="1 0 0 1"/><texture /></material></visual>'
    )
    arm, _ = _load_quietly(_toy(tmp_path, _chain(("j1", "j2", "j3"), visual)))
    assert "texture" not in arm.urdf_text and 'rgba="1 0 0 1"' in arm.urdf_text
    world = PegWorld(arm, WorldConfig(T=2), (0.3, 0.0, 0.0))
    world.close()


def test_meshes_pybullet_cannot_read_are_dropped_with_one_warning(tmp_path: Path) -> None:
    """A .glb visual would make PyBullet refuse the whole URDF."""
    (tmp_path / "part.glb").write_bytes(b"glTF")
    visual = '<visual><geometry><mesh filename="part.glb"/></geometry></visual>'
    arm, caught = _load_quietly(_toy(tmp_path, _chain(("j1", "j2", "j3"), visual)))
    assert len(caught) == 1 and "'part.glb'" in caught[0] and "PyBullet cannot read" in caught[0]
    assert ".glb" not in arm.urdf_text
    world = PegWorld(arm, WorldConfig(T=2), (0.3, 0.0, 0.0))
    world.close()


def test_a_robot_finger_whose_joints_are_all_finger_joints_is_an_arm(tmp_path: Path) -> None:
    names = ("finger_base_to_upper", "finger_upper_to_middle", "finger_middle_to_lower")
    arm, _ = _load_quietly(_toy(tmp_path, _chain(names)))
    assert arm.joint_names == names and arm.ee_link == "l3"


def test_the_tool_frame_is_preferred_to_a_gripper_base_and_a_wrist_camera(tmp_path: Path) -> None:
    """Links fixed to the wrist, equally deep: the gripper's base (a finger below it on a
    prismatic joint, a camera fixed deeper) and a range sensor are listed first, the tool
    frame (nothing below) is the end effector, as on dexmate's Vega arms and Baxter."""
    body = _chain(("j1", "j2", "j3"))
    for link in ("grasp_base", "hand_range_link", "tool0", "left_finger_link", "wrist_camera_link"):
        body += LINK.format(n=link, extra="")
    for name, parent, child in (
        ("grasp_joint", "l3", "grasp_base"),
        ("range_joint", "l3", "hand_range_link"),
        ("tool0_joint", "l3", "tool0"),
        ("camera_joint", "grasp_base", "wrist_camera_link"),
    ):
        body += f'<joint name="{name}" type="fixed"><parent link="{parent}"/><child link="{child}"/></joint>'
    body += JOINT.format(
        n="left_finger",
        t="prismatic",
        p="grasp_base",
        c="left_finger_link",
        xyz="0 0 0",
        axis="1 0 0",
    )
    arm, _ = _load_quietly(_toy(tmp_path, body))
    assert arm.ee_link == "tool0"


@pytest.mark.parametrize("seed", range(6))
def test_fuzzed_tool_extensions_load_or_give_one_error(tmp_path: Path, seed: int) -> None:
    """A published arm with other tools' prefixed attributes and elements put at random
    places, some visual materials' names emptied and some meshes renamed to formats PyBullet
    cannot read: it loads with the same joints and a text PyBullet and pytorch-kinematics
    accept."""
    rng = random.Random(seed)
    text = UR5E.read_text()
    tags = [m.end() for m in re.finditer(r"<(link|joint|visual|limit)\b[^>]*?(?=/?>)", text)]
    for at in sorted(rng.sample(tags, 6), reverse=True):
        prefix = rng.choice(["drake", "mujoco", "isaac", "sdf"])
        text = text[:at] + f' {prefix}:extra="{rng.random()}"' + text[at:]
    end = text.rfind("</robot>")
    text = (
        text[:end]
        + '<mujoco:compiler angle="radian"/><isaac:x a="1"><isaac:y/></isaac:x>'
        + text[end:]
    )
    text = re.sub(
        r'(<mesh filename="[^"]*)\.obj"',
        lambda m: m.group(1) + rng.choice([".obj", ".glb", ".ply", ".OBJ"]) + '"',
        text,
    )
    path = tmp_path / "arms" / "ur5e" / "ur5e.urdf"
    path.parent.mkdir(parents=True)
    path.write_text(text)
    arm, _ = _load_quietly(path)
    assert len(arm.joint_names) == 6
    assert not re.search(r"\b(drake|mujoco|isaac|sdf):|xmlns", arm.urdf_text)
    config = TaskConfig(urdf=str(path), world=WorldConfig(T=2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        task = PegTask(config, n_worlds=1)
    try:
        assert fk_gap(task, 2) < 1e-6
    finally:
        task.close()


def test_run_folder_copy_of_a_description_with_undeclared_prefixes_loads(tmp_path: Path) -> None:
    """The run folder's copy (meshes made absolute) is parsed with the prefixes declared, and
    loads as the original does."""
    folder = tmp_path / "ur5e"
    (folder / "visual").mkdir(parents=True)
    text = UR5E.read_text()
    mesh = re.search(r'filename="(visual/[^"]+)"', text)
    assert mesh is not None
    (folder / mesh.group(1)).write_text("o empty\n")
    (folder / "ur5e.urdf").write_text(text)
    copy = portable_urdf(str(folder / "ur5e.urdf"))
    assert str(folder / mesh.group(1)) in copy
    (tmp_path / "arm.urdf").write_text(copy)
    arm, _ = _load_quietly(tmp_path / "arm.urdf")
    assert arm.joint_names == _load_quietly(UR5E)[0].joint_names


def _kr16_effort(tmp_path: Path, joint: str, effort: str) -> Path:
    """ROS-Industrial's KR 16 with ``joint``'s ``effort="0"`` replaced by ``effort`` (an
    attribute with its leading space, or "")."""
    pattern = rf'(<joint name="{joint}".*?<limit) effort="0"'
    text, found = re.subn(pattern, rf"\1{effort}", KR16.read_text(), count=1, flags=re.S)
    assert found == 1
    path = tmp_path / "kr16.urdf"
    path.write_text(text)
    return path


def test_unknown_torque_limits_are_derived_from_the_arm_with_one_warning_each(
    tmp_path: Path,
) -> None:
    """ROS-Industrial's KR 16 gives ``effort="0"`` on its six joints; here one joint gives no
    effort at all.  Each gets the limit derived from the arm (positive, finite, also in the
    URDF text PyBullet and pytorch-kinematics read), one warning per joint names it and the
    value, and a short rollout at full torque stays finite."""
    path = _kr16_effort(tmp_path, "joint_a3", "")
    arm, caught = _load_quietly(path)
    effort = [m for m in caught if "effort" in m]
    assert len(effort) == 6
    for name, value, message in zip(arm.joint_names, arm.effort, effort, strict=True):
        assert f"joint {name!r}" in message and f"using {value:.4g} N m" in message
    assert all(0 < e < float("inf") for e in arm.effort) and arm.effort == derived_effort(arm)
    limits = {
        joint.get("name"): joint.find("limit")
        for joint in ET.fromstring(arm.urdf_text).iter("joint")
    }
    assert tuple(float(limits[n].get("effort", "nan")) for n in arm.joint_names) == arm.effort
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ArmWarning)
        task = PegTask(TaskConfig(urdf=str(path), world=WorldConfig(T=10)), n_worlds=1)
    try:
        limit = torch.tensor(arm.effort, dtype=torch.float64)
        bang = lambda t, x, rows: limit * (-1) ** t * torch.ones(x.shape[0], 6, dtype=torch.float64)  # noqa: E731
        assert torch.isfinite(task.sample(bang, [(0.0, 0.0)]).x).all()
    finally:
        task.close()


@pytest.mark.parametrize(
    ("effort", "message"),
    [
        ("-5", "joint 'joint_a2': <limit> effort must not be negative, got -5.0"),
        ("abc", "joint 'joint_a2': <limit> effort='abc' is not a number"),
    ],
)
def test_a_bad_torque_limit_gets_one_error_line(
    tmp_path: Path, effort: str, message: str, run_script: ScriptRunner
) -> None:
    path = _kr16_effort(tmp_path, "joint_a2", f' effort="{effort}"')
    assert message in _one_error_line(run_script, path)


@pytest.mark.parametrize(
    "urdf", ["robots/kuka_peg.urdf", str(Path(DATA, "franka_panda/panda.urdf"))]
)
def test_the_simulated_arm_has_no_visual_shapes_and_moves_as_with_them(urdf: str) -> None:
    """PyBullet reads every mesh file it is given (seconds for large ones): the learning
    worlds load the arm without its visual shapes, the pictures' world (``meshes=True``) with
    them, and both simulate bit for bit alike (the default KUKA, primitive visuals, and
    pybullet_data's Panda, mesh visuals)."""
    arm, _ = _load_quietly(urdf)
    mid = (torch.tensor(arm.lower) + torch.tensor(arm.upper)).numpy() / 2
    torques = (
        0.3
        * torch.tensor(arm.effort)
        * torch.randn(20, arm.dof, generator=torch.Generator().manual_seed(0))
    )
    runs, shapes = [], []
    for meshes in (False, True):
        world = PegWorld(arm, WorldConfig(), (0.5, 0.0, 0.0), meshes=meshes)
        shapes.append(pb.getVisualShapeData(world.body, physicsClientId=world.client))
        runs.append([world.reset(mid), *(world.step(u.numpy()) for u in torques)])
        world.close()
    # without visuals PyBullet shows the peg's collision shape, the only one
    assert len(shapes[0]) == 1 and len(shapes[1]) > 1
    assert all((a == b).all() for a, b in zip(*runs, strict=True))


def _without_inertials(text: str, links: tuple[str, ...]) -> str:
    """``text`` with the ``<inertial>`` of each of ``links`` removed (as text: some published
    files use XML prefixes they do not declare)."""
    for name in links:
        start = text.index(f'<link name="{name}"')
        end = text.index("</link>", start)
        link = re.sub(r"<inertial>.*?</inertial>", "", text[start:end], flags=re.DOTALL)
        text = text[:start] + link + text[end:]
    return text


@pytest.mark.parametrize("how", ["no inertial", "mass 0"])
def test_massless_last_link_is_warned_about_and_the_arm_runs(tmp_path: Path, how: str) -> None:
    """A driven link without ``<inertial>`` (Kinova's Gen3 lite publishes its last link so) is
    massless, the URDF default: its joint still moves the peg, so the arm loads with one
    warning naming the link, is massless in PyBullet (which alone would put 1 kg there) and
    runs an iteration."""
    text = UR5E.read_text()
    if how == "no inertial":
        text = _without_inertials(text, ("wrist_3_link",))
    else:
        start = text.index('<link name="wrist_3_link">')
        end = text.index("</link>", start)
        link = re.sub(r'<mass value="[^"]*"', '<mass value="0"', text[start:end])
        text = text[:start] + link + text[end:]
    path = tmp_path / "ur5e.urdf"
    path.write_text(text)
    arm, caught = _load_quietly(path)
    massless = [w for w in caught if "taken as massless" in w]
    assert len(massless) == 1 and "'wrist_3_link'" in massless[0], caught
    client = pb.connect(pb.DIRECT)
    try:
        (tmp_path / "arm.urdf").write_text(arm.urdf_text)
        body = pb.loadURDF(str(tmp_path / "arm.urdf"), useFixedBase=True,
                           flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=client)  # fmt: skip
        names = [pb.getJointInfo(body, i, physicsClientId=client)[12].decode()
                 for i in range(pb.getNumJoints(body, physicsClientId=client))]  # fmt: skip
        index = names.index("wrist_3_link")
        assert pb.getDynamicsInfo(body, index, physicsClientId=client)[0] == 0.0
    finally:
        pb.disconnect(client)
    check_published_arm(str(path), 6, "tool0")


def test_actuated_joint_that_moves_no_mass_is_one_error_line(
    tmp_path: Path, run_script: ScriptRunner
) -> None:
    """The KUKA carrying its own peg, with the last link, its flange, the peg and the peg tip
    all without ``<inertial>``: the last joint would move nothing."""
    massless = ("iiwa_link_7", "iiwa_link_ee", "peg", "peg_tip")
    text = _without_inertials(Path("robots/kuka_peg.urdf").read_text(), massless)
    path = tmp_path / "massless_wrist.urdf"
    path.write_text(text)
    error = _one_error_line(run_script, path)
    assert "joint 'iiwa_joint_7' moves no mass" in error
    assert "add the mass and inertia of 'iiwa_link_7'" in error


def test_massless_wrist_whose_mass_matrix_is_singular_is_one_error_line(
    tmp_path: Path, run_script: ScriptRunner
) -> None:
    """The KR 6 with masses on its first three links only: its massless wrist's axes align at
    q = 0, where some joint motion then moves no mass; one error line names the links."""
    inertial = (
        '<inertial><mass value="5"/><inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" '
        'iyz="0"/></inertial>'
    )
    text = KR6.read_text()
    for link in ("link_1", "link_2", "link_3"):
        text = text.replace(f'<link name="{link}">', f'<link name="{link}">{inertial}', 1)
    urdf = tmp_path / "kr6_heavy_base.urdf"
    urdf.write_text(text)
    error = _one_error_line(run_script, urdf)
    assert "'link_4', 'link_5', 'link_6' massless" in error
    assert "the mass matrix is singular at q = [0, 0, 0, 0, 0, 0] rad" in error
