"""Dataset export: HDF5 round trip, Minari compatibility, bad input, interrupted writes."""

from __future__ import annotations

import hashlib
import io
import json
import multiprocessing
import os
import runpy
import shutil
import signal
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from lolgps_torch.data import (
    ReplayBuffer,
    export_hdf5,
    export_minari,
    load_dataset,
)
from lolgps_torch.data.run_folder import RunFolder, portable_urdf, task_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.progress import progress
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.sim.world import WorldConfig
from lolgps_torch.state import StateLayout
from lolgps_torch.task import PegTask, TaskConfig, task_config_from_dict
from lolgps_torch.types import ConditionSamples, DistillBatch, Trajectories, VisitedRows

F64 = torch.float64
ROOT = Path(__file__).resolve().parents[1]
URDF = str(ROOT / "robots" / "kuka_peg.urdf")
SCRIPT = ROOT / "scripts" / "export_dataset.py"
THRESHOLD = WorldConfig().success_threshold
# Hole offsets (m) and trajectory counts of the synthetic run; condition 1 kept no samples.
OFFSETS = [(0.0, 0.0), (0.01, -0.01), (-0.02, 0.015)]
COUNTS = [3, 0, 4]


def make_samples(M: int, T: int, has_pre: bool, seed: int) -> ConditionSamples:
    """Random samples of the 7-joint arm (dX = 26, dU = 7); final distances straddle the
    success threshold so that filtering by success has something to do."""
    g = torch.Generator().manual_seed(seed)
    dX, dU = 26, 7
    A = torch.randn(M, T, dU, dU, dtype=F64, generator=g)
    pre = float(has_pre)
    return ConditionSamples(
        x=torch.randn(M, T, dX, dtype=F64, generator=g),
        u=torch.randn(M, T, dU, dtype=F64, generator=g),
        cost=torch.rand(M, T, dtype=F64, generator=g),
        final_distance=torch.linspace(0.0, 2 * THRESHOLD, M, dtype=F64),
        mean_cur=torch.randn(M, T, dU, dtype=F64, generator=g),
        prec_cur=A @ A.mT + torch.eye(dU, dtype=F64),
        mean_pre=pre * torch.randn(M, T, dU, dtype=F64, generator=g),
        prec_pre=pre * (A.mT @ A + torch.eye(dU, dtype=F64)),
        has_pre=torch.full((M,), has_pre),
        final_state=torch.randn(M, dX, dtype=F64, generator=g),
    )


def make_run(folder: Path, T: int, counts: list[int]) -> Path:
    """A run folder as scripts/run_stream.py leaves it: config.json and replay.h5."""
    folder.mkdir(parents=True)
    task = TaskConfig(urdf=URDF)
    task = replace(task, world=replace(task.world, T=T))
    config = {
        "method": "lolgps",
        "seed": 0,
        "task": asdict(task),
        "stream": {},
        "conditions": [list(o) for o in OFFSETS[: len(counts)]],
        "stages": [],
    }
    (folder / "config.json").write_text(json.dumps(config))
    replay = ReplayBuffer(folder / "replay.h5")
    for index, M in enumerate(counts):
        samples = make_samples(M, T, has_pre=index > 0, seed=index)
        replay.append_condition(
            index, OFFSETS[index], samples, iterations=5 + index, visited=visited_rows(samples)
        )
    return folder


def visited_rows(samples: ConditionSamples) -> VisitedRows:
    """Labelled states as an S-step's visits store them: here, the samples' last step."""
    last = (samples.x, samples.mean_cur, samples.prec_cur, samples.mean_pre, samples.prec_pre)
    batch = DistillBatch(*(f[:, -1] for f in last), has_pre=samples.has_pre)
    M, T = samples.x.shape[:2]
    return VisitedRows(batch, torch.zeros(M, dtype=torch.int64), torch.full((M,), T - 1))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_run(tmp_path_factory.mktemp("export") / "run", T=6, counts=COUNTS)


@pytest.fixture(scope="module")
def exported(run_dir: Path) -> Path:
    out = run_dir.parent / "dataset.h5"
    report = export_hdf5(run_dir, out)
    assert (report.trajectories, report.steps) == (sum(COUNTS), sum(COUNTS) * 6)
    return out


def replay_rows(run_dir: Path) -> dict[int, ConditionSamples]:
    replay = ReplayBuffer(run_dir / "replay.h5")
    return {i: replay.read_condition(i).samples for i in replay.conditions()}


def states_of(samples: ConditionSamples) -> torch.Tensor:
    """The T+1 states ``[M, T+1, dX]`` of replay samples."""
    assert samples.final_state is not None
    return torch.cat([samples.x, samples.final_state[:, None]], 1)


def test_round_trip_gives_the_replay(run_dir: Path, exported: Path) -> None:
    data, meta = load_dataset(exported)
    replay = replay_rows(run_dir)
    pairs = {
        "actions": "u",
        "cost": "cost",
        "final_distance": "final_distance",
        "mean_cur": "mean_cur",
        "prec_cur": "prec_cur",
        "mean_pre": "mean_pre",
        "prec_pre": "prec_pre",
        "has_pre": "has_pre",
    }
    for index, samples in replay.items():
        rows = data.condition == index
        assert int(rows.sum()) == COUNTS[index]
        assert torch.equal(data.states[rows], states_of(samples))
        for ours, theirs in pairs.items():
            a, b = getattr(data, ours)[rows], getattr(samples, theirs)
            assert a.dtype == b.dtype and torch.equal(a, b), ours
        assert torch.equal(data.total_cost[rows], samples.cost.sum(-1))
        assert torch.equal(data.success[rows], samples.final_distance < THRESHOLD)
        offset = torch.tensor(OFFSETS[index], dtype=F64).expand(COUNTS[index], 2)
        assert torch.equal(data.hole_offset[rows], offset)

    arm = load_arm(URDF)
    layout = StateLayout(arm.dof)
    assert meta["schema_version"] == 2 and meta["method"] == "lolgps"
    assert meta["arm"]["joint_names"] == list(arm.joint_names)
    assert meta["arm"]["ee_link"] == arm.ee_link
    text = meta["arm"]["urdf_text"]
    assert meta["arm"]["urdf_sha256"] == hashlib.sha256(text.encode()).hexdigest()
    assert meta["arm"]["source_urdf_sha256"] == hashlib.sha256(Path(URDF).read_bytes()).hexdigest()
    assert meta["state"]["names"] == layout.names()
    assert meta["state"]["points"] == [layout.points.start, layout.points.stop]
    assert (meta["task"]["dt"], meta["task"]["substeps"], meta["task"]["T"]) == (0.05, 5, 6)
    assert meta["cost"] == asdict(TaskConfig(urdf=URDF).cost)
    assert meta["run_config"] == json.loads((run_dir / "config.json").read_text())
    assert [c["hole_offset"] for c in meta["conditions"]] == [list(o) for o in OFFSETS]
    assert [c["n_trajectories"] for c in meta["conditions"]] == COUNTS
    mouth = np.array(meta["arm"]["nominal_hole_mouth"])
    for c in meta["conditions"]:
        assert np.allclose(c["hole_mouth"], mouth + [*c["hole_offset"], 0.0])


def test_the_visited_states_are_exported(run_dir: Path, exported: Path) -> None:
    replay = ReplayBuffer(run_dir / "replay.h5")
    stored = [replay.read_condition(i).visited for i in replay.conditions()]
    with h5py.File(exported, "r") as f:
        group = f["visited"]
        assert group["states"].shape[0] == sum(v.R for v in stored if v is not None)
        want = torch.cat([v.rows.prec_cur for v in stored if v is not None])
        assert torch.equal(torch.from_numpy(group["prec_cur"][()]), want)
        assert set(group) == {"states", "mean_cur", "prec_cur", "mean_pre", "prec_pre",
                              "has_pre", "condition", "t"}  # fmt: skip


def test_load_filters_by_condition_and_success(exported: Path) -> None:
    everything, _ = load_dataset(exported)
    data, _ = load_dataset(exported, conditions=[2], success_only=True)
    want = (everything.condition == 2) & (everything.final_distance < THRESHOLD)
    assert 0 < int(want.sum()) < COUNTS[2]
    for name, tensor in data._asdict().items():
        assert torch.equal(tensor, getattr(everything, name)[want]), name
    empty, _ = load_dataset(exported, conditions=[1])
    assert empty.states.shape == (0, 7, 26)
    with pytest.raises(LolgpsError, match="holds no condition 7"):
        load_dataset(exported, conditions=[7])


def test_minari_load_dataset_iterates_every_episode(
    run_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    minari = pytest.importorskip("minari")
    report = export_minari(run_dir, tmp_path / "peg-test-v0")
    N, T = sum(COUNTS), 6
    assert (report.trajectories, report.steps) == (N, N * T)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("peg-test-v0")
    assert (dataset.total_episodes, dataset.total_steps) == (N, N * T)
    assert dataset.observation_space.shape == (26,) and dataset.action_space.shape == (7,)
    expected = [
        row
        for c in replay_rows(run_dir).values()
        for row in zip(states_of(c), c.u, c.cost, strict=True)
    ]
    episodes = list(dataset.iterate_episodes())
    assert len(episodes) == N and sum(len(ep) for ep in episodes) == dataset.total_steps
    for episode, (x, u, cost) in zip(episodes, expected, strict=True):
        assert np.array_equal(episode.observations, x.numpy())
        assert np.array_equal(episode.actions, u.numpy())
        assert np.array_equal(episode.rewards, -cost.numpy())
        assert not episode.terminations.any() and episode.truncations.tolist() == [0] * 5 + [1]
    meta = list(dataset.storage.get_episode_metadata(range(N)))
    assert [int(m["condition"]) for m in meta] == [0] * 3 + [2] * 4
    assert dataset.storage.metadata["lolgps_torch"]["schema_version"] == 2
    spec = dataset.env_spec
    assert spec.id == "lolgps_torch/PegInsertion-v0" and spec.max_episode_steps == T
    task = task_config_from_dict(spec.kwargs["task_config"])
    assert task.world.T == T and Path(task.urdf).is_absolute()
    assert Path(task.urdf).read_bytes() == Path(URDF).read_bytes()


def as_samples(rollouts: Trajectories, rows: slice) -> ConditionSamples:
    """Rollouts as replay samples, with no controller labels (zeros)."""
    x, u = rollouts.x[rows], rollouts.u[rows]
    dU = u.shape[-1]
    zeros = torch.zeros(*u.shape[:2], dU, dU, dtype=F64)
    return ConditionSamples(
        x=x,
        u=u,
        cost=rollouts.cost[rows],
        final_distance=rollouts.final_distance[rows],
        mean_cur=torch.zeros_like(u),
        prec_cur=zeros + torch.eye(dU, dtype=F64),
        mean_pre=torch.zeros_like(u),
        prec_pre=zeros,
        has_pre=torch.zeros(x.shape[0], dtype=torch.bool),
        final_state=rollouts.final_state[rows],
    )


def test_recovered_env_replays_every_episode(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Rollouts of random torques (two worlds, so one world runs two of them), exported with
    their run folder's URDF copy; each episode's actions, replayed in the recovered
    environment from its reset options, give its observations and final tip distance."""
    minari = pytest.importorskip("minari")
    config = TaskConfig(urdf=URDF)
    config = replace(config, world=replace(config.world, T=30))
    offsets = [(0.02, 0.02), (-0.01, 0.0), (0.0, -0.015)]
    task = PegTask(config, n_worlds=2)
    effort = torch.tensor(task.arm.effort, dtype=F64)
    g = torch.Generator().manual_seed(0)
    torques = 0.3 * effort * torch.randn(3, 30, 7, dtype=F64, generator=g)
    rollouts = task.sample(lambda t, x, rows: torques[rows, t], offsets)
    task.close()
    folder = RunFolder(tmp_path / "run")
    urdf_text = portable_urdf(URDF)
    run_config = {"method": "lolgps", "seed": 0, "task": task_json(config, urdf_text)}
    folder.start({**run_config, "conditions": [list(o) for o in offsets]}, urdf_text)
    replay = ReplayBuffer(folder.replay_path)
    for index, offset in enumerate(offsets):
        replay.append_condition(index, offset, as_samples(rollouts, slice(index, index + 1)), 1)
    export_minari(folder.path, tmp_path / "peg-real-v0")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("peg-real-v0")
    assert dataset.env_spec.kwargs["task_config"]["urdf"] == str(folder.urdf_path.resolve())
    env = dataset.recover_environment()
    meta = dataset.storage.get_episode_metadata(range(3))
    for episode, info in zip(dataset.iterate_episodes(), meta, strict=True):
        obs, _ = env.reset(options=info["options"])
        observations = [obs]
        for action in episode.actions:
            obs, _, _, truncated, step_info = env.step(action)
            observations.append(obs)
        assert truncated
        assert np.allclose(observations, episode.observations, rtol=0.0, atol=1e-6)
        assert abs(step_info["tip_distance"] - info["final_distance"]) < 1e-6
    env.close()


def test_schema_1_files_still_load(exported: Path, tmp_path: Path) -> None:
    """A version-1 file (the first T states only) loads with its T states."""
    old = tmp_path / "v1.h5"
    shutil.copyfile(exported, old)
    with h5py.File(old, "a") as f:
        f.attrs["schema_version"] = 1
        states = f["trajectories/states"][()]
        del f["trajectories/states"]
        f["trajectories"].create_dataset("states", data=states[:, :-1])
    data, meta = load_dataset(old)
    assert meta["schema_version"] == 1
    assert torch.equal(data.states, load_dataset(exported)[0].states[:, :-1])


def test_replay_without_final_states_is_refused(run_dir: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    shutil.copyfile(run_dir / "config.json", run / "config.json")
    samples = make_samples(2, 6, has_pre=False, seed=0)._replace(final_state=None)
    ReplayBuffer(run / "replay.h5").append_condition(0, OFFSETS[0], samples, iterations=1)
    with pytest.raises(LolgpsError, match="before replays kept the state after the last action"):
        export_hdf5(run, tmp_path / "out.h5")
    assert not (tmp_path / "out.h5").exists()


def test_corrupt_and_foreign_datasets_raise(exported: Path, tmp_path: Path) -> None:
    truncated = tmp_path / "truncated.h5"
    data = exported.read_bytes()
    truncated.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(LolgpsError, match="cannot read dataset"):
        load_dataset(truncated)
    other = tmp_path / "other.h5"
    shutil.copyfile(exported, other)
    with h5py.File(other, "a") as f:
        f.attrs["schema_version"] = 3
    with pytest.raises(LolgpsError, match="schema version 3"):
        load_dataset(other)
    with pytest.raises(LolgpsError, match="not a lolgps_torch dataset"):
        load_dataset(exported.parent / "run" / "replay.h5")
    with pytest.raises(LolgpsError, match="not found"):
        load_dataset(tmp_path / "absent.h5")


def test_overwrite_needs_force(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "out.h5"
    out.write_bytes(b"keep me")
    with pytest.raises(LolgpsError, match="already exists"):
        export_hdf5(run_dir, out)
    assert out.read_bytes() == b"keep me"
    export_hdf5(run_dir, out, force=True)
    assert load_dataset(out)[0].states.shape[0] == sum(COUNTS)
    folder = tmp_path / "peg-test-v0"
    folder.mkdir()
    with pytest.raises(LolgpsError, match="already exists"):
        export_minari(run_dir, folder)
    export_minari(run_dir, folder, force=True)
    assert (folder / "data" / "metadata.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.h5", "peg-test-v0"]


def run_script(args: list[str], monkeypatch: pytest.MonkeyPatch) -> int:
    """Run the export script in this process; its exit status."""
    monkeypatch.setattr(sys, "argv", ["export_dataset.py", *args])
    try:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    except SystemExit as exit_info:
        return int(exit_info.code or 0)
    return 0


@pytest.mark.parametrize("case", ["missing", "truncated", "other_version", "exists"])
def test_script_prints_one_error_line(
    case: str,
    run_dir: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    run, out = tmp_path / "run", tmp_path / "out.h5"
    if case != "missing":
        shutil.copytree(run_dir, run)
    replay = run / "replay.h5"
    if case == "truncated":
        replay.write_bytes(replay.read_bytes()[:-4096])
    elif case == "other_version":
        with h5py.File(replay, "a") as f:
            f.attrs["version"] = 99
    elif case == "exists":
        out.write_bytes(b"")
    code = run_script(["--run", str(run), "--out", str(out)], monkeypatch)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("error: "), err
    assert out.exists() == (case == "exists")


def test_script_reports_what_it_wrote(
    run_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    out = tmp_path / "out.h5"
    out.write_bytes(b"")
    assert run_script(["--run", str(run_dir), "--out", str(out), "--force"], monkeypatch) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"wrote {out}: 7 trajectories, 42 steps,") and line.endswith(" s")


@pytest.mark.parametrize("fmt", ["hdf5", "minari"])
def test_killed_export_leaves_nothing_at_the_output(
    fmt: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """SIGKILL a forked export while its temporary output exists: nothing at the output path."""
    if fmt == "minari":
        pytest.importorskip("minari")
    big = tmp_path_factory.getbasetemp() / "big_run"
    if not big.exists():
        make_run(big, T=100, counts=[30, 30])
    work = tmp_path_factory.mktemp(f"killed_{fmt}")
    out = work / ("out.h5" if fmt == "hdf5" else "peg-big-v0")
    partial = work / ("out.h5.partial" if fmt == "hdf5" else ".peg-big-v0.partial")
    export = export_hdf5 if fmt == "hdf5" else export_minari
    proc = multiprocessing.get_context("fork").Process(target=export, args=(big, out))
    proc.start()
    assert proc.pid is not None
    try:
        while not partial.exists() and proc.is_alive():
            time.sleep(0.002)
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(timeout=30)
    finally:
        if proc.is_alive():
            proc.kill()
    assert proc.exitcode == -signal.SIGKILL, "the export finished before it could be killed"
    assert partial.exists() and not out.exists()
    export(big, out)  # the next export replaces the stale temporary
    assert out.exists() and not partial.exists()


@pytest.mark.parametrize("tty", [True, False])
def test_progress_bar_only_on_a_terminal(tty: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    class Stream(io.StringIO):
        def isatty(self) -> bool:
            return tty

    stream = Stream()
    monkeypatch.setattr(sys, "stderr", stream)
    items = [1, 2, 3]
    wrapped = progress(items, len(items), "demo")
    assert list(wrapped) == items
    assert (wrapped is items) == (not tty)
    assert ("demo" in stream.getvalue()) == tty
