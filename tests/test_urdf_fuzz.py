"""Malformed URDFs: each is refused with one :class:`LolgpsError`, or it loads and survives
building the task and a short rollout, never a traceback or a crash.

100 seeded random mutations of ``robots/kuka_peg.urdf`` (a number replaced, a tag deleted or
duplicated, an attribute dropped, a name duplicated, a joint re-linked, the file truncated)
go through the loader here; the accepted ones are built and rolled out in one forked process,
so a simulator segfault fails the test instead of killing it.
"""

from __future__ import annotations

import copy
import json
import multiprocessing
import random
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.ik import solve_ik
from lolgps_torch.robot.placement import PlacementConfig
from lolgps_torch.sim.world import WorldConfig
from lolgps_torch.task import PegTask, TaskConfig

KUKA = Path(__file__).resolve().parent.parent / "robots" / "kuka_peg.urdf"
N_MUTATIONS = 100  # about a quarter load, each built and rolled out in 0.3-0.5 s
# the KUKA's start pose from inverse kinematics, given so the worker skips the IK solve
KUKA_Q0 = (-0.00347, 0.32111, 0.00470, -1.36089, -0.00149, 1.45942, -0.04466)
BAD_NUMBERS = ("nan", "inf", "-inf", "0", "-1", "abc", "1.2.3", "")
NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


@dataclass(frozen=True)
class Mutation:
    """A mutated URDF written to ``path``; ``what`` says how it was made."""

    path: Path
    what: str


def _elements(robot: ET.Element) -> list[tuple[ET.Element, ET.Element]]:
    """Every (parent, element) pair below the root."""
    return [(parent, child) for parent in robot.iter() for child in parent]


def _replace_number(robot: ET.Element, rng: random.Random) -> str:
    slots = [
        (el, attr, m.span())
        for el in robot.iter()
        for attr, value in el.attrib.items()
        for m in NUMBER.finditer(value)
    ]
    el, attr, (a, b) = rng.choice(slots)
    bad = rng.choice(BAD_NUMBERS)
    value = el.attrib[attr]
    el.set(attr, (value[:a] + bad + value[b:]).strip())
    return f"<{el.tag} name={el.get('name')}> {attr}={value!r} -> {el.get(attr)!r}"


def _delete_tag(robot: ET.Element, rng: random.Random) -> str:
    parent, el = rng.choice(_elements(robot))
    parent.remove(el)
    return f"deleted <{el.tag} {el.attrib}> from <{parent.tag} {parent.get('name')}>"


def _duplicate_tag(robot: ET.Element, rng: random.Random) -> str:
    parent, el = rng.choice(_elements(robot))
    parent.insert(list(parent).index(el) + 1, copy.deepcopy(el))
    return f"duplicated <{el.tag} {el.attrib}> in <{parent.tag} {parent.get('name')}>"


def _drop_attribute(robot: ET.Element, rng: random.Random) -> str:
    el = rng.choice([el for el in robot.iter() if el.attrib])
    attr = rng.choice(sorted(el.attrib))
    del el.attrib[attr]
    return f"dropped {attr} from <{el.tag} {el.attrib}>"


def _duplicate_name(robot: ET.Element, rng: random.Random) -> str:
    tag = rng.choice(("link", "joint"))
    first, second = rng.sample(robot.findall(tag), 2)
    second.set("name", first.get("name", ""))
    return f"{tag} names duplicated: {first.get('name')!r}"


def _relink(robot: ET.Element, rng: random.Random) -> str:
    joint = rng.choice(robot.findall("joint"))
    end = rng.choice(("parent", "child"))
    link = rng.choice([*(el.get("name", "") for el in robot.findall("link")), "nowhere"])
    el = joint.find(end)
    assert el is not None
    el.set("link", link)
    return f"joint {joint.get('name')!r} {end} -> {link!r}"


MUTATORS = (_replace_number, _replace_number, _delete_tag, _duplicate_tag, _drop_attribute)
MUTATORS += (_duplicate_name, _relink)


def mutate(seed: int) -> tuple[str, str]:
    """Mutated URDF text and a description; one in 16 is truncated text."""
    rng = random.Random(seed)
    text = KUKA.read_text()
    if rng.random() < 1 / 16:
        cut = rng.randrange(len(text))
        return text[:cut], f"truncated at {cut}"
    robot = ET.fromstring(text)
    what = rng.choice(MUTATORS)(robot, rng)
    return ET.tostring(robot, encoding="unicode"), what


@pytest.fixture(scope="module")
def mutations(tmp_path_factory: pytest.TempPathFactory) -> list[Mutation]:
    folder = tmp_path_factory.mktemp("fuzz")
    out = []
    for seed in range(N_MUTATIONS):
        text, what = mutate(seed)
        path = folder / f"m{seed:03d}.urdf"
        path.write_text(text)
        out.append(Mutation(path, what))
    return out


def _loader_outcomes(mutations: list[Mutation]) -> dict[Path, str | None]:
    """The loader's message for each refused mutation, None for each accepted one."""
    outcomes: dict[Path, str | None] = {}
    for m in mutations:
        try:
            load_arm(str(m.path))
            outcomes[m.path] = None
        except LolgpsError as exc:
            outcomes[m.path] = str(exc)
    return outcomes


@pytest.mark.parametrize("count", [50, pytest.param(N_MUTATIONS, marks=pytest.mark.slow)])
def test_mutations_are_refused_or_survive_a_rollout(
    mutations: list[Mutation], tmp_path: Path, count: int
) -> None:
    """The first ``count`` mutations (half of them in the default suite, all in slow)."""
    mutations = mutations[:count]
    loader = _loader_outcomes(mutations)
    for m in mutations:
        message = loader[m.path]
        assert message is None or (str(m.path) in message and "\n" not in message), (m, message)
    accepted = [m for m in mutations if loader[m.path] is None]
    out = tmp_path / "outcomes.jsonl"
    paths = [str(m.path) for m in accepted]
    worker = multiprocessing.get_context("fork").Process(target=_worker, args=(str(out), paths))
    worker.start()
    worker.join(timeout=600)
    worker.kill()  # if it hangs
    lines = out.read_text().splitlines() if out.exists() else []
    results = [json.loads(line) for line in lines]
    died_on = accepted[len(results)].what if len(results) < len(accepted) else None
    assert worker.exitcode == 0, (died_on, worker.exitcode)
    assert [r["path"] for r in results] == [str(m.path) for m in accepted]
    crashes = [
        (m.what, r) for m, r in zip(accepted, results, strict=True) if r["outcome"] == "crash"
    ]
    assert not crashes
    survived = sum(r["outcome"] == "survived" for r in results)
    # both kinds must be common, or the mutations no longer probe the loader
    refused = len(mutations) - len(accepted)
    assert refused >= 0.4 * count and survived >= 0.15 * count, (refused, survived)


def _variant(tmp_path: Path, old: str, new: str) -> str:
    """The KUKA with the first ``old`` replaced by ``new``."""
    text = KUKA.read_text()
    assert old in text
    path = tmp_path / "variant.urdf"
    path.write_text(text.replace(old, new, 1))
    return str(path)


JOINT_3 = 'name="iiwa_joint_3"'
LINK_1_VISUAL = '<geometry><cylinder radius="0.07" length="0.2025"/></geometry>'
LINK_3_INERTIA = 'ixx="0.08" ixy="0" ixz="0" iyy="0.075" iyz="0" izz="0.01"'
JOINT_2_LIMIT = 'lower="-2.0943951023931953" upper="2.0943951023931953" effort="320"'
LINK_0_VISUAL = '<geometry><cylinder radius="0.07" length="0.1575"/></geometry>'


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (JOINT_3, 'name="iiwa_joint_2"', "joint name 'iiwa_joint_2' is used twice"),
        ('name="iiwa_link_3"', 'name="iiwa_link_2"', "link name 'iiwa_link_2' is used twice"),
        (
            LINK_1_VISUAL,
            LINK_1_VISUAL.replace(
                "</geometry>", '<cylinder radius="0.07" length="0.2"/></geometry>'
            ),
            "link 'iiwa_link_1': <visual>: <geometry> needs exactly one shape, "
            "found <cylinder>, <cylinder>",
        ),
        (
            LINK_3_INERTIA,
            LINK_3_INERTIA.replace(' iyz="0"', ""),
            "link 'iiwa_link_3': <inertial>: <inertia> has no iyz attribute",
        ),
        (
            '<origin xyz="0 0 0.2155"',
            '<origin xyz="0 0 inf"',
            "joint 'iiwa_joint_4': <origin> xyz='0 0 inf' is not finite",
        ),
        (
            '<origin xyz="0 0 0.1575" rpy="0 0 0"/>\n    <axis',
            '<origin xyz="0 0.1575" rpy="0 0 0"/>\n    <axis',
            "joint 'iiwa_joint_1': <origin> xyz='0 0.1575' needs 3 number(s), got 2",
        ),
        (
            '<mass value="1.7"/>',
            '<mass value="1.7"/><mass value="1.7"/>',
            "link 'iiwa_link_5': <inertial>: more than one <mass>",
        ),
        ('<mass value="1.7"/>', "", "link 'iiwa_link_5': <inertial>: <mass> missing"),
        (
            LINK_3_INERTIA,
            LINK_3_INERTIA.replace('ixy="0"', 'ixy="0.1"'),
            "link 'iiwa_link_3': inertia is not positive semi-definite",
        ),
        (
            JOINT_2_LIMIT,
            'lower="1" upper="1" effort="320"',
            "joint 'iiwa_joint_2': <limit> lower 1.0 is not below upper 1.0",
        ),
        (
            JOINT_2_LIMIT,
            JOINT_2_LIMIT.replace("320", "-320"),
            "joint 'iiwa_joint_2': <limit> effort must not be negative",
        ),
        (
            ' velocity="1.4835298641951802"',
            "",
            "joint 'iiwa_joint_1': <limit> has no velocity attribute",
        ),
        (
            '<axis xyz="0 0 1"/>',
            '<axis xyz="0 0 0"/>',
            "joint 'iiwa_joint_1': <axis> xyz is (nearly) the zero",
        ),
        (
            '<parent link="iiwa_link_0"/>',
            '<parent link="iiwa_link_9"/>',
            "joint 'iiwa_joint_1': parent link 'iiwa_link_9' is not defined",
        ),
        (
            '<parent link="iiwa_link_0"/>',
            '<parent link="iiwa_link_2"/>',
            "joints form a cycle through links ['iiwa_link_1', 'iiwa_link_2'",
        ),
        (
            '<material name="iiwa_grey"/>',
            "<material/>",
            "link 'iiwa_link_0': <visual>: <material> has no name",
        ),
    ],
)
def test_bad_urdf_is_refused_naming_the_element(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    path = _variant(tmp_path, old, new)
    with pytest.raises(LolgpsError) as exc:
        load_arm(path)
    assert str(exc.value).startswith(f"{path}: ") and message in str(exc.value)


def test_massless_link_fixed_to_a_moving_one_is_accepted(tmp_path: Path) -> None:
    """As on pybullet_data's Panda: only a link a joint drives needs mass."""
    load_arm(_variant(tmp_path, '<mass value="0.001"/>', '<mass value="0"/>'))


@pytest.mark.parametrize("name", ["meshes/base.obj", "package://kuka/meshes/base.obj"])
def test_mesh_paths_resolve_beside_the_urdf(tmp_path: Path, name: str) -> None:
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "base.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    arm = load_arm(
        _variant(tmp_path, LINK_0_VISUAL, f'<geometry><mesh filename="{name}"/></geometry>')
    )
    assert f'filename="{tmp_path / "meshes" / "base.obj"}"' in arm.urdf_text


def _hold(dof: int) -> Callable[[int, torch.Tensor, slice], torch.Tensor]:
    """Zero torque on top of the world's gravity compensation: the arm holds its pose."""
    return lambda t, x, rows: torch.zeros(x.shape[0], dof, dtype=torch.float64)


def _worker(out: str, paths: list[str]) -> None:
    """Build the task and run a 5-step rollout for each URDF; one JSON line per URDF to ``out``
    (not stdout, where PyBullet prints its warnings)."""
    for path in paths:
        try:
            dof = load_arm(path).dof  # a re-linked joint can shorten the chain: solve IK then
            q0 = KUKA_Q0 if dof == len(KUKA_Q0) else None
            config = TaskConfig(urdf=path, world=WorldConfig(T=5), placement=PlacementConfig(q0=q0))
            task = PegTask(config, n_worlds=1)
            traj = task.sample(_hold(dof), [(0.0, 0.0)])
            solve_ik(task.kinematics, task.arm, task.targets([(0.0, 0.0)])[0], 0.0, iterations=3)
            task.effective_inertia()
            task.close()
            finite = bool(torch.isfinite(traj.x).all() and torch.isfinite(traj.cost).all())
            outcome, detail = ("survived", "") if finite else ("crash", "non-finite rollout")
        except LolgpsError as exc:
            outcome, detail = "refused", str(exc)
        except Exception as exc:  # the failure this test exists to catch
            outcome, detail = "crash", f"{type(exc).__name__}: {exc}"
        with open(out, "a") as fh:
            fh.write(json.dumps({"path": path, "outcome": outcome, "detail": detail}) + "\n")
