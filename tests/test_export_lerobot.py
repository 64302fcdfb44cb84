"""The LeRobot export (``export_dataset.py --format lerobot``): LeRobot's own loader
(``LeRobotDataset`` of the ``lerobot-dataset`` package), offline, reads the export of a run
and gives, episode for episode and frame for frame, the successful trajectories of its
``replay.h5``; ``--video`` adds a camera stream of one frame per step; bad input is one line."""

from __future__ import annotations

import importlib.util
import math
import os
import re
import sys
import types
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ScriptRun
from test_export import URDF, make_run

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.export_lerobot import export_lerobot, frames_per_second
from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.sim.world import WorldConfig
from lolgps_torch.state import StateLayout

os.environ["HF_HUB_OFFLINE"] = "1"  # before huggingface_hub is imported: no network
os.environ["HF_DATASETS_OFFLINE"] = "1"

T, FPS = 6, 20  # the synthetic run's steps, and 1 / dt for its dt = 0.05 s
THRESHOLD = WorldConfig().success_threshold
TIP = StateLayout(7).points  # the state's tip block p_tip - p*_tip, then the top's


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run whose replay holds 3, 0 and 4 samples at three conditions, of which 1, 0 and 2
    end within the success threshold."""
    return make_run(tmp_path_factory.mktemp("lerobot") / "run", T=T, counts=[3, 0, 4])


def successful(run_dir: Path) -> list[tuple[int, tuple[float, float], torch.Tensor, int]]:
    """``(condition, hole offset, samples, row)`` of every successful sample of the run's
    replay, in the replay's order."""
    replay = ReplayBuffer(run_dir / "replay.h5")
    found = []
    for condition in replay.conditions():
        record = replay.read_condition(condition)
        for row in torch.nonzero(record.samples.final_distance < THRESHOLD).flatten().tolist():
            found.append((condition, record.offset, record.samples, row))
    return found


@pytest.fixture(scope="module")
def loader(tmp_path_factory: pytest.TempPathFactory) -> type:
    """LeRobot's ``LeRobotDataset``, its Hugging Face caches in a temporary folder.
    lerobot-dataset imports torchvision, which it does not declare, for images and videos
    only; where torchvision is not installed (its Linux wheels in the package index are CUDA
    builds, which do not import beside a CPU-only torch) an empty stand-in lets the loader
    read numeric features unchanged."""
    pytest.importorskip("ledataset")
    os.environ["HF_HOME"] = str(tmp_path_factory.mktemp("hf_home"))
    if importlib.util.find_spec("torchvision") is None:
        import datasets  # noqa: F401  (first: it records torchvision as absent)

        stand_in = types.ModuleType("torchvision")
        stand_in.transforms = types.ModuleType("torchvision.transforms")  # type: ignore[attr-defined]
        sys.modules["torchvision"] = stand_in
        sys.modules["torchvision.transforms"] = stand_in.transforms  # type: ignore[attr-defined]
    from ledataset.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset  # type: ignore[no-any-return]


def test_lerobots_loader_reads_the_replays_successful_trajectories(
    run_dir: Path, tmp_path: Path, loader: type
) -> None:
    """One episode per successful sample, in the replay's order: its frames are the T steps
    at 1/dt per second with the state, the action and the cost rounded to float32, whether
    the next state's tip is within the threshold, and the last step done; its task names the
    hole offset, two conditions' episodes sharing none."""
    report = export_lerobot(run_dir, tmp_path / "peg")
    expected = successful(run_dir)
    assert [c for c, *_ in expected] == [0, 2, 2]
    assert (report.trajectories, report.steps) == (3, 3 * T)
    dataset = loader("lolgps/peg", root=tmp_path / "peg")
    assert (dataset.fps, dataset.num_episodes, len(dataset)) == (FPS, 3, 3 * T)
    assert dataset.meta.total_tasks == 2
    arm = load_arm(URDF)
    assert dataset.features["action"]["names"] == list(arm.joint_names)
    assert dataset.features["observation.state"]["names"] == StateLayout(arm.dof).names()
    for episode, (condition, offset, samples, row) in enumerate(expected):
        meta = dataset.meta.episodes[episode]
        assert (meta["condition"], meta["length"]) == (condition, T)
        assert meta["final_distance"] == float(samples.final_distance[row])
        states = torch.cat([samples.x[row], samples.final_state[row][None]]).numpy()
        for t in range(T):
            frame = dataset[meta["dataset_from_index"] + t]
            assert (frame["episode_index"].item(), frame["frame_index"].item()) == (episode, t)
            assert math.isclose(frame["timestamp"].item(), t / FPS, rel_tol=1e-6)
            assert np.array_equal(frame["observation.state"].numpy(), states[t].astype(np.float32))
            assert np.array_equal(
                frame["action"].numpy(), samples.u[row, t].numpy().astype(np.float32)
            )
            assert frame["cost"].item() == np.float32(samples.cost[row, t].item())
            tip = np.linalg.norm(states[t + 1, TIP][:3])
            assert frame["next.success"].item() == bool(tip < THRESHOLD)
            assert frame["next.done"].item() == (t == T - 1)
            numbers = re.findall(r"-?\d+\.\d+(?:e-?\d+)?", frame["task"])
            assert tuple(float(v) for v in numbers) == offset
    actions = np.concatenate([s.u[r].numpy() for _, _, s, r in expected]).astype(np.float32)
    stats = dataset.meta.stats["action"]
    np.testing.assert_allclose(stats["mean"], actions.astype(np.float64).mean(0), rtol=1e-12)
    np.testing.assert_array_equal(stats["max"], actions.max(0))
    assert stats["count"].tolist() == [3 * T]


def test_video_adds_a_camera_stream_of_one_frame_per_step(
    run_dir: Path, tmp_path: Path, loader: type, run_script: Callable[..., ScriptRun]
) -> None:
    """``--video``: one H.264 stream of the 3 episodes' 6 steps each at 20 frames per second,
    each episode's frames at its place in the stream; the loader finds it."""
    av = pytest.importorskip("av")
    pytest.importorskip("imageio_ffmpeg")
    out = tmp_path / "peg"
    result = run_script("scripts/export_dataset.py", "--run", str(run_dir), "--format",
                        "lerobot", "--out", str(out), "--video", "--size", "64", "48")  # fmt: skip
    assert result.code == 0, result.err
    assert result.out.startswith(f"wrote {out}: 3 trajectories, {3 * T} steps")
    dataset = loader("lolgps/peg", root=out)
    key = "observation.images.camera"
    assert dataset.meta.video_keys == [key]
    assert dataset.features[key]["shape"] == (48, 64, 3)
    starts = [dataset.meta.episodes[e][f"videos/{key}/from_timestamp"] for e in range(3)]
    assert starts == [0.0, T / FPS, 2 * T / FPS]
    with av.open(str(dataset.root / dataset.meta.get_video_file_path(0, key))) as video:
        stream = video.streams.video[0]
        assert (stream.codec_context.name, stream.average_rate) == ("h264", FPS)
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(stream)]
    assert len(frames) == 3 * T and frames[0].shape == (48, 64, 3)
    assert (
        max(np.abs(a.astype(int) - b).mean() for a, b in zip(frames[:-1], frames[1:], strict=True))
        > 1
    )  # moves


def test_bad_input_is_one_line(
    run_dir: Path, tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    out = tmp_path / "peg"
    out.mkdir()
    args = ["scripts/export_dataset.py", "--run", str(run_dir), "--format", "lerobot"]
    result = run_script(*args, "--out", str(out))
    assert (result.code, result.err) == (
        2,
        f"error: {out} already exists; pass --force (force=True) to overwrite it\n",
    )
    result = run_script(*args, "--out", str(tmp_path / "other"), "--video", "--size", "63", "48")
    assert result.code == 2 and result.err.startswith("error: ") and result.err.count("\n") == 1
    result = run_script("scripts/export_dataset.py", "--run", str(run_dir), "--out",
                        str(tmp_path / "other.h5"), "--video")  # fmt: skip
    assert (result.code, result.err) == (2, "error: --video goes with --format lerobot, not hdf5\n")
    with pytest.raises(LolgpsError, match=r"1/dt = 33\.3333"):
        frames_per_second(0.03)
    assert frames_per_second(0.05) == 20 and frames_per_second(0.001) == 1000
