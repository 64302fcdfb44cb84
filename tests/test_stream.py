"""The LOLGPS stream end to end at CI size, its resume after SIGKILL, and its determinism."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pybullet_data
import pytest
import torch
from conftest import ScriptRun, ci_stream_command, finish_script, start_script

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.checkpoint import load_policy
from lolgps_torch.lolgps.distillation import Labels
from lolgps_torch.lolgps.onpolicy import Checked, CheckedSStep, Visit
from lolgps_torch.lolgps.stream import Outcome, StreamLearner, Successes
from lolgps_torch.policy import GaussianPolicy, PolicyConfig
from lolgps_torch.types import Trajectories

SCRIPT = [sys.executable, "scripts/run_stream.py", "--urdf", "robots/kuka_peg.urdf"]


@pytest.fixture(scope="module")
def small_run(ci_stream: Path) -> Path:
    return ci_stream


def test_ci_stream_distils_and_replays_both_conditions(small_run: Path) -> None:
    out = small_run / "run"
    replay = ReplayBuffer(out / "replay.h5")
    assert replay.conditions() == [0, 1]
    # each group keeps the condition's final controllers; p_pre once a policy existed
    first, second = replay.read_condition(0), replay.read_condition(1)
    assert first.p_cur is not None and first.p_pre is None
    assert second.p_cur is not None and second.p_pre is not None
    summary = json.loads((out / "summary.json").read_text())["conditions"]
    assert [e["condition"] for e in summary] == [0, 1]
    # learning happened: the first condition's local controller inserts the peg
    assert summary[0]["first_success_iteration"] is not None
    assert summary[0]["local_success"]
    for index in (0, 1):
        policy = load_policy(out / "checkpoints" / f"after_condition_{index:03d}")
        assert policy.trained
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    iterations = [r for r in records if "iteration" in r]
    assert {"time_sample", "time_fit", "time_cstep", "mean_cost"} <= set(iterations[0])
    assert sum(r.get("event") == "distilled" for r in records) == 2
    config = json.loads((out / "config.json").read_text())
    assert config["conditions"] == [[0.0, 0.0], [0.01, -0.01]]


def test_a_run_reads_back_at_the_hole_and_start_pose_it_was_placed_at(small_run: Path) -> None:
    from dataclasses import replace

    from lolgps_torch.lolgps.run import load_run
    from lolgps_torch.robot.placement import place_task

    run = load_run(small_run / "run")
    placement = run.info.task.placement
    assert placement.mouth is not None and placement.q0 is not None
    task = run.make_task(n_worlds=1)
    try:
        assert task.geometry.nominal_mouth == placement.mouth and task.geometry.q0 == placement.q0
        # the same as placing anew today, and kept even where the placement would now differ
        unpinned = replace(placement, mouth=None, q0=None)
        depth = run.info.task.world.depth
        fresh = place_task(task.arm, task.kinematics, unpinned, depth)
        assert fresh.nominal_mouth == pytest.approx(placement.mouth, abs=1e-12)
        moved = replace(placement, reach_fraction=0.45)
        assert place_task(task.arm, task.kinematics, moved, depth) == task.geometry
    finally:
        task.close()


def test_precision_share_splits_the_teachers_precision_over_the_windows(
    small_run: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """The windows asked for, each share in [0, 1], summing to 1 over the whole rollout and
    to less over part of it; windows that do not rise within the rollout are refused."""
    cmd = ["scripts/research/precision_share.py", str(small_run / "run")]
    whole, part = (
        run_script(*cmd, "--edges", *edges) for edges in (["0", "10", "100"], ["5", "50"])
    )
    assert whole.code == 0 and part.code == 0, whole.err[-2000:] + part.err[-2000:]
    windows = whole.out.strip().split("by steps: ")[1].split(", ")
    assert [w.split()[0] for w in windows] == ["0-9", "10-99"]
    shares = [float(w.split()[1]) for w in windows]
    assert all(0.0 <= s <= 1.0 for s in shares) and sum(shares) == pytest.approx(1.0, abs=0.011)
    assert 0.0 <= float(part.out.strip().split("5-49 ")[1]) < 1.0
    bad = run_script(*cmd, "--edges", "0", "101")
    assert bad.code == 2
    assert bad.err.strip() == "error: --edges must rise from 0 or more to at most 100, got [0, 101]"


@pytest.mark.slow  # a second CI stream; test_kill_resume's resumed run also ends at its summary
def test_same_seed_gives_same_summary(small_run: Path, tmp_path: Path) -> None:
    log = tmp_path / "again.log"
    process = start_script(ci_stream_command(tmp_path, tmp_path / "again"), log)
    assert finish_script(process, log) == 0, log.read_text()[-2000:]
    first = (small_run / "run" / "summary.json").read_text()
    second = (tmp_path / "again" / "summary.json").read_text()
    assert first == second


def _group_bytes(path: Path, group: str) -> dict[str, bytes]:
    with h5py.File(path, "r") as f:
        return {name: np.asarray(ds).tobytes() for name, ds in f[group].items()}


def test_existing_run_without_resume_is_refused(
    small_run: Path, tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    result = run_script(*ci_stream_command(tmp_path, small_run / "run")[1:])
    assert result.code == 2
    assert result.err.strip().splitlines()[-1].startswith("error: ")
    assert "--resume" in result.err


@pytest.mark.slow
def test_redistill_refits_and_tests_a_finished_run(small_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "refit"
    cmd = [sys.executable, "scripts/research/redistill.py", "--run", str(small_run / "run")]
    proc = subprocess.run(
        [*cmd, "--steps", "50", "--out", str(out)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert lines[0].startswith("fitted ") and lines[-1].startswith("training positions ")
    assert sum(line.startswith("condition ") for line in lines) == 2
    assert load_policy(out).trained
    bad = subprocess.run([*cmd, "--steps", "0"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and bad.stderr.strip().startswith("error: ")


def test_trace_policy_prints_rollout_and_fit_per_condition(
    small_run: Path, run_script: Callable[..., ScriptRun]
) -> None:
    cmd = ["scripts/research/trace_policy.py", "--run", str(small_run / "run")]
    result = run_script(*cmd, "--steps", "0", "5")
    assert result.code == 0, result.err[-2000:]
    lines = result.out.strip().splitlines()
    assert lines[0] == "policy after condition 1; columns: steps [0, 5]"
    assert [line.split()[1] for line in lines[1::3]] == ["0", "1"]
    # the rollout starts at the start pose, whose tip error at step 0 is the same for both
    # conditions up to the hole offsets (0, 0) and (0.01, -0.01): 10 mm apart in x and y
    x0, y0 = (float(v) for v in lines[1].split("mm (")[1].split(",")[:2])
    x1, y1 = (float(v) for v in lines[4].split("mm (")[1].split(",")[:2])
    assert (x0 - x1, y0 - y1) == pytest.approx((10.0, -10.0), abs=1.0)
    # every rollout, and every D_g sample, starts at the start pose: inside the support
    assert all(line.strip().startswith("support (sd) 0.0 ") for line in lines[2::3])
    assert all(line.strip().startswith("D_g fit: ") for line in lines[3::3])
    bad = run_script(*cmd, "--steps", "100")
    assert bad.code == 2 and bad.err.strip() == "error: --steps must lie in [0, 100), got [100]"


def test_teachers_measures_each_teacher_and_its_nearest(
    small_run: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """Each of the two conditions is the other's nearest; its lateral error is a tip distance
    in mm; the free part of their difference is zero at the shared start pose and about the
    same size from either side later; each teacher's approach ends within the rollout (the
    tip within 5 mm of the hole's axis: these teachers succeed); bad steps are refused."""
    cmd = ["scripts/research/teachers.py", str(small_run / "run")]
    result = run_script(*cmd, "--steps", "0", "5", "99")
    assert result.code == 0, result.err[-2000:]
    lines = result.out.strip().splitlines()
    assert "nearest 1)" in lines[1] and lines[1].strip().startswith("condition 0 (")
    assert "nearest 0)" in lines[2] and lines[2].strip().startswith("condition 1 (")
    lateral = [float(line.split("lateral ")[1].split(";")[0]) for line in lines[1:3]]
    assert all(0.0 <= side < 1000.0 for side in lateral)
    first, second = (
        [float(v) for v in line.split("free ")[1].split(";")[0].split()] for line in lines[1:3]
    )
    assert first[0] == second[0] == 0.0  # both start at the start pose
    assert all(v >= 0.0 for v in first + second) and first[2] == pytest.approx(second[2], rel=0.5)
    aligned = [int(line.split("aligned ")[1]) for line in lines[1:3]]
    assert all(0 < step < 100 for step in aligned)
    assert lines[3].strip().startswith("mean lateral ")
    assert lines[3].strip().endswith(f"aligned at steps {min(aligned)}-{max(aligned)}")
    bad = run_script(*cmd, "--steps", "100")
    assert bad.code == 2 and bad.err.strip() == "error: --steps must lie in [0, 100), got [100]"


def test_mouth_finds_where_teachers_and_policy_come_down_to_the_mouth(
    small_run: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """The successful teachers reach the mouth's height over the hole (within its 4 mm
    clearance) at the step the descent schedule brings the lifted targets there,
    ``t_d (1 - depth / h_0)``, a step or two either side; the policy's line and the summary
    count what the lines show."""
    result = run_script("scripts/research/mouth.py", str(small_run / "run"))
    assert result.code == 0, result.err[-2000:]
    task = json.loads((small_run / "run" / "config.json").read_text())["task"]
    cost, depth = task["cost"], task["world"]["depth"]
    due = cost["descent_steps"] * (1.0 - depth / cost["descent_height"])
    lines = result.out.strip().splitlines()
    rows = [line.split("teachers ")[1] for line in lines[1:3]]
    teachers = [(int(r.split(",")[0]), float(r.split(",")[1].split(";")[0])) for r in rows]
    assert all(abs(step - due) <= 2.5 and 0.0 <= side < 4.0 for step, side in teachers)
    policy = [line.split("policy ")[1].split(",") for line in lines[1:3]]
    finals = [float(p[2].split()[0]) for p in policy]
    wide = sum(1 for p in policy if p[0] == "None" or float(p[1]) > 4.0)
    steps = [step for step, _ in teachers]
    assert lines[3].strip().startswith(f"teachers steps {min(steps)}-{max(steps)}, ")
    assert f"{wide} of 2 policy arrivals beyond the 4 mm clearance" in lines[3]
    assert lines[3].endswith(f"{sum(f < 0.06 for f in finals)} of 2 reached")


@pytest.mark.slow
def test_trace_policy_traces_an_areas_misses(small_run: Path, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    shutil.copytree(small_run / "run", run_dir)
    trace = [sys.executable, "scripts/research/trace_policy.py", "--run", str(run_dir)]
    cmd = [*trace, "--area-misses", "1"]
    missing = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert missing.returncode == 2 and missing.stderr.strip().startswith(
        f"error: {run_dir}/eval.json: no test area 1 to trace"
    )
    evaluate = [sys.executable, "scripts/evaluate.py", "--run", str(run_dir)]
    area_args = ["--areas", "2", "--per-area", "4", "--workers", "1"]
    done = subprocess.run([*evaluate, *area_args], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    proc = subprocess.run([*cmd, "--steps", "0", "5"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()
    finals = json.loads((run_dir / "eval.json").read_text())["stages"][-1]["per_position"]
    missed = sum(d >= 0.06 for d in finals["final_distance"][1])
    assert lines[0] == f"stream policy, area 1: {missed}/4 missed"
    rollouts = [line for line in lines if "from a training position: rollout tip error" in line]
    assert len(rollouts) == missed


ARMS = {
    "kuka": "robots/kuka_peg.urdf",
    "panda": str(Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"),
    "xarm6": str(Path(pybullet_data.getDataPath()) / "xarm" / "xarm6_robot.urdf"),
}


@pytest.mark.long
@pytest.mark.parametrize("arm", sorted(ARMS))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_default_stream_policy_succeeds_at_7_of_8(arm: str, seed: int, tmp_path: Path) -> None:
    """The main job on each arm, with only ``--urdf``: after the default 8-condition stream
    the global policy alone succeeds at >= 7 of the 8 training positions. 2-5 minutes each,
    more on a loaded machine: marked long."""
    out = tmp_path / "run"
    cmd = [*SCRIPT[:2], "--urdf", ARMS[arm], "--seed", str(seed), "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-2000:]
    entries = json.loads((out / "summary.json").read_text())["conditions"]
    assert len(entries) == 8
    assert sum(bool(e["policy_success_end"]) for e in entries) >= 7


class _ScriptedDistiller:
    """A scripted S-step for :class:`CheckedSStep`, with one stored condition: it writes the
    round's number into the policy's first bias and records its arguments."""

    config = PolicyConfig()

    def __init__(self) -> None:
        self.calls: list[tuple[int, frozenset[int], int | None, object]] = []

    def stored(self) -> list[SimpleNamespace]:
        samples = SimpleNamespace(x=torch.zeros(1, 2, 3))
        return [SimpleNamespace(condition=0, offset=(0.0, 0.0), samples=samples, p_cur=None)]

    def __call__(self, policy, new, seed, emphasis=frozenset(), config=None, visited=None):  # type: ignore[no-untyped-def]
        self.calls.append((seed, emphasis, config.steps if config else None, visited))
        with torch.no_grad():
            policy.net[0].bias[0] = len(self.calls) - 1
        policy.trained = True
        return [float(len(self.calls))]


def _checked(
    distances: list[list[float]], repairs: int, rounds: int = 0
) -> tuple[Checked, _ScriptedDistiller, GaussianPolicy]:
    """Run :class:`CheckedSStep` with scripted S-steps and visits: closed-loop distances at
    the replay's position and the new one, and one labelled row (a marker) per visit."""
    distill, scripted, policy = _ScriptedDistiller(), iter(distances), GaussianPolicy(3, 1)

    def visits(policy, teachers, seed, label):  # type: ignore[no-untyped-def]
        assert [t.offset for t in teachers] == [(0.0, 0.0), (0.01, 0.0)]
        return Visit(next(scripted), f"rows of {seed}" if label else None, 2, 0.0)

    sstep = CheckedSStep(distill, visits, 0.06, rounds > 0, rounds, repairs)  # type: ignore[arg-type]
    item = SimpleNamespace(offset=(0.01, 0.0), data=SimpleNamespace(x=torch.zeros(1, 2, 3)),
                           labels=None)  # fmt: skip
    return sstep(policy, item, seed=5), distill, policy  # type: ignore[arg-type]


def test_a_missed_condition_is_repaired_with_its_rows_twice() -> None:
    checked, distill, policy = _checked([[0.001, 0.2], [0.3, 0.2], [0.001, 0.001]], repairs=3)
    assert checked == ([3.0], [0.001, 0.001], 2, None, 6, 0.0)
    # the first S-step in full; repairs from the best so far, a third of the steps, the missed
    # condition (place 1: the new one, after the replay's) emphasised
    steps = PolicyConfig().steps
    assert distill.calls == [(5, frozenset(), None, None),
                             (5 + 1_000_003, frozenset({1}), steps // 3, None),
                             (5 + 2_000_006, frozenset({1}), steps // 3, None)]  # fmt: skip
    assert float(policy.net[0].bias[0]) == 2.0  # the round that reached both is kept


def test_without_a_better_round_the_first_policy_is_kept() -> None:
    checked, _, policy = _checked([[0.001, 0.2], [0.3, 0.2], [0.001, 0.25]], repairs=2)
    assert checked[:3] == ([1.0], [0.001, 0.2], 2)
    assert float(policy.net[0].bias[0]) == 0.0
    checked, distill, _ = _checked([[0.001, 0.2]], repairs=0)
    assert checked.rounds == 0 and len(distill.calls) == 1


def test_onpolicy_rounds_run_and_refit_on_every_visit_so_far(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(  # the scripted rows are markers: joining them lists them
        "lolgps_torch.lolgps.onpolicy.VisitedRows.cat", staticmethod(lambda parts: list(parts))
    )
    reached = [0.001, 0.001]
    checked, distill, _ = _checked([reached, reached, reached], repairs=0, rounds=2)
    assert checked.rounds == 2 and checked.rollouts == 6
    assert [call[3] for call in distill.calls] == [
        None,
        ["rows of 5"],
        ["rows of 5", "rows of 1000008"],
    ]
    assert checked.visited == ["rows of 5", "rows of 1000008", "rows of 2000011"]


def test_retention_script_tabulates_every_checkpoint(
    small_run: Path, tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    run = shutil.copytree(small_run / "run", tmp_path / "run")
    result = run_script("scripts/retention.py", "--run", str(run))
    assert result.code == 0, result.err[-2000:]
    table = json.loads((run / "retention.json").read_text())
    assert len(table["distance"]) == len(table["fit"]) == 2
    assert all(len(row) == 2 for row in table["distance"] + table["fit"])
    summary = json.loads((run / "summary.json").read_text())["conditions"]
    # the last row is the final policy: the stream's own end-of-run distances
    assert table["distance"][-1] == pytest.approx(
        [c["policy_final_distance_end"] for c in summary], rel=1e-9
    )
    assert (run / "retention.png").stat().st_size > 10_000
    assert "forgotten:" in result.out


def test_scale_table_reads_a_run(small_run: Path, run_script: Callable[..., ScriptRun]) -> None:
    script = ["scripts/research/scale_table.py", "--run", str(small_run / "run")]
    result = run_script(*script, "--at", "1", "2", "--window", "1")
    assert result.code == 0, result.err[-2000:]
    rows = [line for line in result.out.splitlines() if line.startswith("| 1 ") or
            line.startswith("| 2 ")]  # fmt: skip
    assert len(rows) == 2


def test_first_divergence_names_the_first_iteration_that_differs(
    small_run: Path, tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """Timings aside, a run against itself never differs; against a copy whose second
    iteration record has another mean cost, that iteration is named."""
    run = small_run / "run"
    script = "scripts/research/first_divergence.py"
    same = run_script(script, str(run), str(run))
    assert same.code == 0 and "iteration records are identical" in same.out, same.err[-2000:]
    copy = tmp_path / "copy"
    copy.mkdir()
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    iterations = [r for r in records if "iteration" in r and "event" not in r]
    iterations[1]["mean_cost"] *= 1.5
    iterations[0]["time_sample"] += 1.0
    (copy / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    result = run_script(script, str(copy), str(run))
    expected = f"condition {iterations[1]['condition']}, iteration {iterations[1]['iteration']} "
    assert result.code == 0 and f"first difference: {expected}" in result.out, result.err
    assert "relative difference 0.5" in result.out


def test_a_final_controller_that_misses_hands_d_g_to_the_newest_tried_one_that_succeeds() -> None:
    """The final p_cur has not been sampled: when its noiseless rollout succeeds it labels D_g;
    when it misses, the p_cur of the newest iteration with successful samples whose noiseless
    rollout succeeds labels instead (a converged controller that later steps degraded), and
    its distance is the condition's; when every one misses, the closest; after a numerical
    failure only the tried ones compete (none: the final, at infinity)."""
    learner = object.__new__(StreamLearner)
    learner.task = SimpleNamespace(config=SimpleNamespace(world=SimpleNamespace(success_threshold=0.06)))  # fmt: skip
    distances = {"final": 0.2, "it0": 0.3, "it1": 0.002, "it2": 0.15}
    asked: list[str] = []
    learner.noiseless = lambda p, offset: asked.append(p) or distances[p]
    found = Successes()
    zeros, one_hit, no_hit = torch.zeros(2, 3), torch.tensor([True, False]), torch.zeros(2) > 0
    for i, name in enumerate(("it0", "it1", "none", "it2")):
        samples = Trajectories(zeros, zeros, zeros, zeros[:, 0], no_hit if name == "none" else one_hit, zeros, no_hit)  # fmt: skip
        found.add(samples, Labels(name, None, i))
    final = Labels("final", None, 5)

    def teacher(failure: str | None = None) -> tuple[object, int, float]:
        asked.clear()
        labels, local = learner.teacher(Outcome(found, final, 30, failure, 0), (0.0, 0.0))
        return labels.p_cur, labels.iteration, local

    assert [labels.iteration for labels in found.tried] == [0, 1, 3]
    assert teacher() == ("it1", 1, 0.002) and asked == ["final", "it2", "it1"]
    distances["final"] = 0.01
    assert teacher() == ("final", 5, 0.01) and asked == ["final"]
    distances["final"], distances["it1"] = 0.1, 0.3
    assert teacher() == ("final", 5, 0.1)  # all miss: the closest
    assert teacher("iteration 4: diverged") == ("it2", 3, 0.15)
    assert learner.teacher(Outcome(Successes(), final, 30, "diverged", 0), (0.0, 0.0)) == (
        final,
        float("inf"),
    )


def test_first_controller_rolls_out_a_runs_first_controller_in_each_simulator(
    small_run: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """The CI run's first controller at its second condition, one batch in each simulator:
    planned on the model, it inserts the peg in both without a blow-up; a condition the run
    does not have is a one-line error."""
    script = "scripts/research/first_controller.py"
    result = run_script(script, "--run", str(small_run / "run"), "--conditions", "1",
                        "--batches", "1")  # fmt: skip
    assert result.code == 0, result.err
    lines = result.out.splitlines()
    assert [line.split()[0] for line in lines] == ["pybullet", "mujoco"]
    for line in lines:
        assert "0/1 batches blew up" in line
        assert float(line.rsplit("success ", 1)[1]) >= 0.5
    missing = run_script(script, "--run", str(small_run / "run"), "--conditions", "9")
    assert missing.code == 2
    assert missing.err.startswith("error: conditions [9] not in the run's 2")


def test_local_convergence_finds_where_each_full_condition_settles(
    tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    """From a run's metrics: the iteration from which the cost stays within the tolerance of
    the last, the first all-successful one; transferred conditions (fewer iterations) left
    out; a folder without runs refused in one line."""
    run = tmp_path / "sweep" / "run"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"stream": {"success_phases": 4}}))
    costs = {0: [3.0, 2.0, 1.5, 1.51], 1: [2.0, 1.9, 1.8, 1.0], 2: [1.2, 1.1]}
    (run / "metrics.jsonl").write_text(
        "\n".join(
            json.dumps(
                {"condition": c, "iteration": i, "mean_cost": v, "success_rate": 1.0 if i else 0.4}
            )
            for c, values in costs.items()
            for i, v in enumerate(values)
        )
    )
    result = run_script("scripts/research/local_convergence.py", str(tmp_path / "sweep"))
    assert result.code == 0, result.err[-2000:]
    rows = [line.split() for line in result.out.splitlines()[1:] if line.startswith("run ")]
    assert [r[1:5] for r in rows] == [["0", "4", "2", "1"], ["1", "4", "3", "1"]]
    assert "2 conditions; settled at iteration: {2: 1, 3: 1}" in result.out
    assert "  3 phases: 1 stopped before settling, 10 sample rollouts saved" in result.out
    empty = run_script("scripts/research/local_convergence.py", str(tmp_path / "none"))
    assert empty.code == 2 and empty.err.strip().endswith(": no run (config.json) in it")
