"""The Franka backend (lolgps_torch/sim/franka.py) against a stand-in FR3 through the real
protocol: pylibfranka talking to franky-sim (tests/franka_stand_in.py), each test with a
server of its own in a private network namespace, stopped when the test's command ends.
The stand-in's tests run apart from the default suite, its server stepping at 1 kHz in real
time: those of a few minutes marked ``franka`` (``python -m pytest -q -m franka``), the
streams of two conditions ``long``."""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import ScriptRun

from lolgps_torch.sim.simulator import WorldConfig

REPO = Path(__file__).resolve().parents[1]
STAND_IN = REPO / "tests" / "franka_stand_in.py"


def _unshare_works() -> bool:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return False
    probe = subprocess.run(["unshare", "-n", "true"], capture_output=True)
    return probe.returncode == 0


_missing = [m for m in ("pylibfranka", "franky_sim") if importlib.util.find_spec(m) is None]


@pytest.fixture
def fr3(tmp_path: Path) -> Path:
    """franky-sim's FR3 MJCF, its meshes named where they are installed; the test skipped
    where the stand-in cannot run."""
    if _missing:
        pytest.skip(f"not installed: {_missing} (pip install -e '.[franka]' franky-sim)")
    if not _unshare_works():
        pytest.skip("unshare -n is not permitted here")
    spec = importlib.util.find_spec("franky_sim")
    assert spec is not None and spec.origin is not None
    assets = Path(spec.origin).parent / "assets"
    text = (assets / "fr3.xml").read_text()
    path = tmp_path / "fr3.xml"
    path.write_text(text.replace('meshdir="assets"', f'meshdir="{assets / "meshes"}"'))
    return path


def in_namespace(*command: str, reflexes: bool = False, timeout: float = 600) -> str:
    """``command`` run beside a stand-in server in a network namespace of its own; its
    output (stdout and stderr), the test failing where it fails."""
    flags = ["--reflexes"] if reflexes else []
    result = subprocess.run(
        ["unshare", "-n", "--", sys.executable, str(STAND_IN), *flags, "--", *command],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    return output


PRELUDE = """
import json, time
import numpy as np
from lolgps_torch.robot.kinematics import PegKinematics
from lolgps_torch.robot.placement import place_task
from lolgps_torch.sim.arm_world import ArmSampler
from lolgps_torch.sim.franka import RealArmConfig
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.task import TaskConfig, load_task_arm
config = TaskConfig(urdf={mjcf!r}, mjcf=True, sim="mujoco", ee_link="hand")
arm = load_task_arm(config)
geometry = place_task(arm, PegKinematics(arm), config.placement, config.world.depth)
real = RealArmConfig(arm="franka", robot_ip="127.0.0.1", yes=True, deadline={deadline})
plant = PlantConfig(limits={limits!r})
sampler = ArmSampler(real, arm, config.world, geometry.nominal_mouth, geometry.q0, "cpu", plant)
world = sampler.worlds[0]
world.set_hole((0.0, 0.0))
q0 = np.asarray(geometry.q0)
"""


# an actor: the torque u at every step, the learner stalling 100 ms at step stall_at
ACT = """
class Act:
    def __init__(self, u, stall_at=-1):
        self.u, self.stall_at = u, stall_at
    def __call__(self, t, x, rows):
        import torch
        if t == self.stall_at:
            time.sleep(0.1)
        return torch.tensor(self.u, dtype=torch.float64)[None]
"""


def run_on_stand_in(
    mjcf: Path, body: str, reflexes: bool = False, deadline: float = 0.2, limits: str = "reflex"
) -> dict[str, object]:
    """The prelude (the FR3's sampler on the stand-in, the learner's deadline ``deadline``,
    its own reflex ``limits``) and ``body``, which prints one JSON line; that line read
    back."""
    script = PRELUDE.format(mjcf=str(mjcf), deadline=deadline, limits=limits)
    script += ACT + textwrap.dedent(body)
    output = in_namespace(sys.executable, "-c", script, reflexes=reflexes)
    (line,) = [line for line in output.splitlines() if line.startswith("{")]
    result: dict[str, object] = json.loads(line)
    result["output"] = output
    return result


LATE = "the learner's next command was"


def late_at_most(fault: object) -> bool:
    """Whether a rollout ran without a fault, or with none but the learner's deadline: on a
    machine loaded by other work the learner may miss it now and then (docs/REAL_ARM.md),
    which the run counts as a failed rollout and goes on."""
    return fault is None or str(fault).startswith(f"the arm stopped: {LATE}")


@pytest.mark.franka
def test_holds_still(fr3: Path) -> None:
    """Connected and moved to the start pose, zero torque over the arm's own gravity
    compensation for 1 s (20 control steps) moves no joint by 1 mrad, at the arm's 1 kHz
    with at most 1 % of the ticks missed.  The hold is the second at the start pose: the first
    move, 0.79 rad of joint 7 from the stand-in's home pose, leaves that joint wound 1 mrad
    into MuJoCo's soft joint friction, which the first torque command releases (measured:
    -1.0 mrad in the first step, then nothing; a property of the stand-in)."""
    result = run_on_stand_in(
        fr3,
        """
        world.reset(q0)
        world.step(np.zeros(7))
        before = world.device.stats()
        x0 = world.reset(q0)
        for _ in range(20):
            x = world.step(np.zeros(7))
        stats = world.device.stats()
        print(json.dumps({"drift": float(np.abs(x[:7] - x0[:7]).max()),
                          "start": float(np.abs(x0[:7] - q0).max()),
                          "ticks": stats.ticks - before.ticks,
                          "missed": stats.missed - before.missed,
                          "fault": world.fault}))
        """,
    )
    assert result["fault"] is None
    assert result["drift"] < 1e-3
    assert result["start"] < 2e-3  # the move back to the start pose
    assert result["ticks"] >= 1000
    assert result["missed"] <= 10  # 1 % (the machine may be loaded)


@pytest.mark.franka
def test_speed_reflex_reported_and_recovered(fr3: Path) -> None:
    """Joint 7 driven past the FR3's velocity limit: the arm's reflex aborts the torque
    command; the rollout ends as a fault in one line, the arm is recovered and moved back,
    and the next rollout runs."""
    result = run_on_stand_in(
        fr3,
        """
        fast = sampler.rollout(Act([0, 0, 0, 0, 0, 0, 12.0]), [(0.0, 0.0)])
        reason = world.fault
        calm = sampler.rollout(Act([0.0] * 7), [(0.0, 0.0)])
        print(json.dumps({"fast": bool(fast.fault[0]), "reason": reason,
                          "calm": world.fault,
                          "back": float(np.abs(calm.x[0, 0, :7].numpy() - q0).max())}))
        """,
        reflexes=True,
        limits="off",  # the arm's reflex, not the learner's (its speed limits are lower)
    )
    assert result["fast"]
    assert late_at_most(result["calm"]), result["calm"]
    assert "joint_velocity_violation" in str(result["reason"])
    assert result["back"] < 2e-3
    assert "counts as failed" in str(result["output"])


@pytest.mark.franka
def test_stalled_learner_ends_rollout(fr3: Path) -> None:
    """The learner stalls 100 ms within a rollout, the server enforcing the protocol's
    timing: the rollout ends as a fault (the arm's loop, keeping the protocol's pace, ends
    the torque command when the learner's command is later than its deadline, 90 ms here),
    and the next rollout runs."""
    result = run_on_stand_in(
        fr3,
        """
        stalled = sampler.rollout(Act([0.0] * 7, stall_at=10), [(0.0, 0.0)])
        reason = world.fault
        after = sampler.rollout(Act([0.0] * 7), [(0.0, 0.0)])
        print(json.dumps({"stalled": bool(stalled.fault[0]), "reason": reason,
                          "after": world.fault}))
        """,
        reflexes=True,
        deadline=0.09,
    )
    assert result["stalled"]
    assert late_at_most(result["after"]), result["after"]
    assert "late" in str(result["reason"])


def run_stream(fr3: Path, out: Path, conditions: list[list[float]], *extra: str) -> list[str]:
    """scripts/run_stream.py's command on the stand-in FR3 at ``conditions``."""
    path = out.parent / f"{out.name}-conditions.json"
    path.write_text(json.dumps(conditions))
    return [
        sys.executable, "scripts/run_stream.py", "--mjcf", str(fr3), "--sim", "mujoco",
        "--ee-link", "hand", "--arm", "franka", "--robot-ip", "127.0.0.1", "--yes",
        "--conditions", str(path), "--out", str(out), "--workers", "1", *extra,
    ]  # fmt: skip


@pytest.mark.franka
def test_learns_one_condition_then_evaluates_on_the_arm(fr3: Path, tmp_path: Path) -> None:
    """One condition in free space, learnt on the arm from two rollouts an iteration: the peg
    tip ends within the success threshold of the hole's floor point, with no fault; then
    evaluate.py runs the policy on the arm at that position. The on-policy visits without
    the policy's noise (the simulated FR3's policy then ends 5 mm from the floor point, 1.5 mm
    with the noisy ones too, 14 mm with none), on the arm's model (``--visits model``): the 3
    visits run in MuJoCo in the learner's process, and the arm runs only samples and checks."""
    out = tmp_path / "run"
    command = run_stream(fr3, out, [[0.0, 0.0]], "--samples", "2", "--max-iterations", "2",
                         "--success-phases", "1", "--repairs", "0", "--onpolicy-noisy", "0",
                         "--visits", "model")  # fmt: skip
    positions = tmp_path / "positions.json"
    positions.write_text("[[0.0, 0.0]]")
    evaluate = [sys.executable, "scripts/evaluate.py", "--run", str(out), "--positions",
                str(positions), "--arm", "franka", "--robot-ip", "127.0.0.1", "--yes"]  # fmt: skip
    both = f"{shlex.join(command)} && {shlex.join(evaluate)}"
    output = in_namespace("sh", "-c", both)
    summary = json.loads((out / "summary.json").read_text())
    (entry,) = summary["conditions"]
    assert entry["local_final_distance"] < 0.06, output
    assert "aborted by reflex" not in output
    assert "rollout 1 on the arm" in output
    assert entry["arm_rollouts"]["visit"] == 0 and entry["model_rollouts"] == 3
    assert summary["model_rollouts"] == 3 and summary["model_faults"] == 0
    # the arm's seconds: at least its rollouts' seconds under torque (T dt each)
    world = WorldConfig()
    rollouts = sum(entry["arm_rollouts"].values())
    assert summary["arm_seconds"] == pytest.approx(entry["arm_seconds"])
    assert entry["arm_seconds"] >= 0.9 * rollouts * world.T * world.dt, output
    assert f"{entry['arm_seconds']:.0f} s on the arm" in output
    evaluation = json.loads((out / "eval.json").read_text())
    (stage,) = evaluation["stages"]
    assert stage["groups"][0]["success_rate"]["mean"] == 1.0, output
    assert stage["faults"] == 0


@pytest.mark.parametrize(
    ("script", "flags", "message"),
    [
        ("run_stream.py", ["--arm", "franka"], "--arm franka needs --robot-ip"),
        (
            "evaluate.py",
            ["--run", "x", "--arm", "franka", "--robot-ip", "10.0.0.2", "--ray"],
            "--ray runs rollouts on Ray actors",
        ),  # fmt: skip
        (
            "run_stream.py",
            ["--arm", "franka", "--robot-ip", "10.0.0.2", "--deadline", "0"],
            "--deadline must be positive",
        ),  # fmt: skip
    ],
)
def test_arm_flags_refused_in_one_line(
    script: str, flags: list[str], message: str, run_script: Callable[..., ScriptRun]
) -> None:
    """Bad arm flags: one error line, exit status 2, before any arm is reached."""
    result = run_script(f"scripts/{script}", *flags)
    assert result.code == 2, result.err
    assert result.err.strip().splitlines()[-1].startswith(f"error: {message}")


def missed_share(output: str) -> float:
    """The share of the arm's ticks missed over the rollouts ``output`` reports."""
    counts = re.findall(r"(\d+) of (\d+) ticks missed", output)
    assert counts, output
    return sum(int(m) for m, _ in counts) / sum(int(n) for _, n in counts)


@pytest.mark.long
def test_learns_two_conditions(fr3: Path, tmp_path: Path) -> None:
    """A two-condition stream in free space: both learnt (the local controller's and the
    global policy's tips within the success threshold of the floor point), no fault, under
    1 % of the arm's ticks missed, the summary written."""
    out = tmp_path / "run"
    command = run_stream(fr3, out, [[0.01, -0.02], [-0.03, 0.04]], "--samples", "3",
                         "--max-iterations", "6", "--success-phases", "3", "--seed", "3")  # fmt: skip
    output = in_namespace(*command, timeout=3600)
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["conditions"]) == 2
    for entry in summary["conditions"]:
        assert entry["local_final_distance"] < 0.06, output
        assert entry["policy_final_distance_end"] < 0.06, output
    assert "aborted by reflex" not in output
    assert missed_share(output) < 0.01


# run_stream.py killed in a rollout of the second condition (6 s after the first report of
# one: the move back takes about 4 s), then resumed
KILL_AND_RESUME = """
import json, signal, subprocess, sys, time
command = json.loads(sys.argv[1])
learner = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
before, done = [], False
for line in learner.stdout:
    before.append(line)
    done = done or line.startswith("condition 1/2 done")
    if done and line.startswith("rollout"):
        time.sleep(6.0)
        break
learner.send_signal(signal.SIGKILL)
learner.wait()
resumed = subprocess.run([*command, "--resume"], capture_output=True, text=True)
print(json.dumps({"before": "".join(before), "after": resumed.stdout + resumed.stderr,
                  "code": resumed.returncode}))
"""


@pytest.mark.franka
def test_killed_mid_rollout_then_resumed(fr3: Path, tmp_path: Path) -> None:
    """The learner killed in the middle of the second condition's rollouts; --resume keeps
    the first condition as it was learnt and redoes the second: the summary holds both. One
    S-step per condition on D_g alone (the paper's): no on-policy visits, each a rollout of
    the stand-in's seconds."""
    out = tmp_path / "run"
    command = run_stream(fr3, out, [[0.0, 0.0], [0.02, 0.02]], "--samples", "2",
                         "--max-iterations", "2", "--success-phases", "1", "--repairs", "0",
                         "--no-onpolicy", "--onpolicy-rounds", "0")  # fmt: skip
    output = in_namespace(sys.executable, "-c", KILL_AND_RESUME, json.dumps(command), timeout=3600)
    (line,) = [line for line in output.splitlines() if line.startswith("{")]
    result = json.loads(line)
    assert result["code"] == 0, result["after"]
    done = re.search(r"condition 1/2 done: .* p_cur distance (\d\.\d+)", result["before"])
    assert done is not None, result["before"]
    assert "condition 1/2  iter" not in result["after"]  # the first condition kept
    assert "condition 2/2 done" in result["after"]
    summary = json.loads((out / "summary.json").read_text())
    first, second = summary["conditions"]
    assert f"{first['local_final_distance']:.4f}" == done.group(1)
    assert second["condition"] == 1
