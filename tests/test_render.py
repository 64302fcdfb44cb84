"""Videos of a run: a short render of a tiny fabricated run decodes with the expected frames,
the peg shows against the background, captions carry the distances the task measures, and an
arm without any visual or collision shape on its links is still drawn."""

from __future__ import annotations

import re
import runpy
import sys
from collections.abc import Iterator
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from lolgps_torch.data.checkpoint import save_policy
from lolgps_torch.data.replay import ReplayBuffer
from lolgps_torch.data.run_folder import RunFolder, portable_urdf, task_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.render import (
    RenderConfig,
    frame_count,
    parse_conditions,
    record_clips,
    render_clips,
)
from lolgps_torch.evaluation.scene import Scene, camera_for
from lolgps_torch.lolgps.run import LoadedRun, load_run
from lolgps_torch.policy.actor import policy_actor
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.robot.ik import solve_ik
from lolgps_torch.robot.peg import PegConfig
from lolgps_torch.sim.pybullet_display import BACKGROUND, BARE_ARM
from lolgps_torch.sim.world import WorldConfig
from lolgps_torch.task import PegTask, TaskConfig
from lolgps_torch.types import ConditionSamples, LinearGaussian

ROOT = Path(__file__).resolve().parents[1]
KUKA = str(ROOT / "robots" / "kuka_peg.urdf")
SCRIPT = ROOT / "scripts" / "render.py"
T = 6  # control steps per episode of the tiny run
OFFSETS = [(0.0, 0.0), (0.03, -0.02)]


def make_run(folder: Path, urdf: str = KUKA) -> None:
    """A run of two conditions with T-step episodes, without learning: config.json, the URDF
    copy, a policy checkpoint per condition (untrained weights) and replay groups whose p_cur
    is the hold controller ``u = 0`` (gravity compensation alone)."""
    task = TaskConfig(urdf=urdf, world=WorldConfig(T=T))
    text = portable_urdf(urdf)
    stages = [{"name": "train0", "last_condition": len(OFFSETS) - 1}]
    config = {"task": task_json(task, text), "conditions": OFFSETS, "stages": stages}
    RunFolder(folder).start({**config, "method": "lolgps", "seed": 0, "stream": {}}, text)
    dof = load_arm(urdf, None, task.peg).dof
    dX, M = 2 * dof + 12, 1
    torch.manual_seed(0)
    replay = ReplayBuffer(RunFolder(folder).replay_path)
    for index, offset in enumerate(OFFSETS):
        save_policy(RunFolder(folder).checkpoint_dir(index), GaussianPolicy(dX, dof))
        z = torch.zeros
        samples = ConditionSamples(
            z(M, T, dX), z(M, T, dof), z(M, T), z(M), z(M, T, dof),
            torch.eye(dof).expand(M, T, dof, dof), z(M, T, dof), z(M, T, dof, dof),
            torch.zeros(M, dtype=torch.bool),
        )  # fmt: skip
        hold = LinearGaussian(z(T, dof, dX), z(T, dof), torch.eye(dof).expand(T, dof, dof))
        replay.append_condition(index, offset, samples, 1, p_cur=hold)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> LoadedRun:
    folder = tmp_path_factory.mktemp("render") / "run"
    make_run(folder)
    return load_run(folder)


@pytest.fixture(scope="module")
def tiny_task(tiny_run: LoadedRun) -> Iterator[PegTask]:
    task = tiny_run.make_task(n_worlds=2)
    yield task
    task.close()


def decode(path: Path) -> list[np.ndarray]:
    """Every frame of an .mp4 (through ffmpeg) or a .gif (Pillow), ``[H, W, 3]`` uint8."""
    if path.suffix == ".gif":
        frames = []
        with Image.open(path) as gif:
            for index in range(getattr(gif, "n_frames", 1)):
                gif.seek(index)
                frames.append(np.asarray(gif.convert("RGB")))
        return frames
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    width, height = next(reader)["size"]
    return [np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader]


@pytest.mark.parametrize(
    ("suffix", "config"),
    [
        (".mp4", RenderConfig(who="both", size=(96, 64), every=2, columns=2)),
        (".gif", RenderConfig(size=(96, 64), layout="sequence")),
    ],
)
def test_a_short_render_decodes_with_the_peg_in_view(
    tiny_run: LoadedRun, tiny_task: PegTask, tmp_path: Path, suffix: str, config: RenderConfig
) -> None:
    if suffix == ".mp4":
        pytest.importorskip("imageio_ffmpeg")  # the video extra (in dev)
    out = tmp_path / f"clip{suffix}"
    clips = record_clips(tiny_run, tiny_task, [0, 1], config.who)
    render_clips(tiny_task, clips, config, out)
    frames = decode(out)
    per_clip = len(range(0, T + 1, config.every)) + (T % config.every != 0)
    n_cells = 4 if config.who == "both" else 2
    expected = per_clip * (n_cells if config.layout == "sequence" else 1)
    assert len(frames) == expected == frame_count(len(clips), T, config)
    W, H = config.size
    columns = min(config.columns, n_cells) if config.layout == "grid" else 1
    rows = -(-n_cells // columns) if config.layout == "grid" else 1
    assert frames[0].shape == (rows * H, columns * W, 3)
    assert [(c.who, c.condition) for c in clips] == (
        [("policy", 0), ("controller", 0), ("policy", 1), ("controller", 1)]
        if config.who == "both"
        else [("policy", 0), ("policy", 1)]
    )
    # the first clip's first frame: where the display shows the peg, the video is not background
    task = tiny_task
    scene = Scene(task.arm, task.config.world, task.geometry.nominal_mouth, config.view)
    try:
        camera = scene.camera(clips[0].offset, clips[0].q[0])
        rgb, segmentation = scene.photograph(camera, W, H)
        peg = scene.peg_mask(segmentation)
    finally:
        scene.close()
    band = slice(H // 4, 3 * H // 4)  # between the captions
    peg, rgb = peg[band], rgb[band]
    assert peg.sum() > 20, "the peg is out of the camera's view"
    cell = frames[0][:H, :W][band].astype(float)
    assert np.abs(cell[peg] - BACKGROUND).sum(axis=1).mean() > 60
    assert np.abs(cell - rgb).mean() < 12  # the cell is that photograph
    for frame in frames:
        assert frame.std() > 10  # no blank frame


def test_clips_carry_the_distances_the_task_measures(
    tiny_run: LoadedRun, tiny_task: PegTask
) -> None:
    """The captions' distances are the clip's states' tip offsets; the final one is what the
    task's own sampling (the stream's measure, summary.json) reports."""
    task = tiny_task
    clips = record_clips(tiny_run, task, [0, 1], "both")
    policy = task.sample(policy_actor(tiny_run.policy(), task.model), OFFSETS).final_distance
    zero = torch.zeros(1, T, task.layout.dU, dtype=torch.float64)
    hold = task.sample(lambda t, x, rows: zero[:, t].expand(len(x), -1), OFFSETS)
    by_who = {(c.who, c.condition): c for c in clips}
    for c in (0, 1):
        assert by_who["policy", c].final_distance == pytest.approx(float(policy[c]), abs=1e-9)
        assert by_who["controller", c].final_distance == pytest.approx(
            float(hold.final_distance[c]), abs=1e-9
        )
        assert by_who["policy", c].q.shape == (T + 1, task.arm.dof)
    assert clips[0].distance[0] == pytest.approx(clips[1].distance[0])  # same start, same hole


def test_the_mouth_view_shows_the_inserted_peg_inside_the_funnel(tiny_task: PegTask) -> None:
    """At the inserted pose (inverse kinematics onto the targets), the close-up sees more of
    the peg than the same camera without the cut: its part below the table's surface."""
    task = tiny_task
    offset = OFFSETS[1]
    q, error = solve_ik(task.kinematics, task.arm, task.targets([offset])[0], margin=0.0)
    assert float(error) < 1e-3
    seen = {}
    for view in ("mouth", "wide"):
        scene = Scene(task.arm, task.config.world, task.geometry.nominal_mouth, view)
        try:
            scene.show(offset, q.numpy())
            mouth = scene.world.nominal_mouth + np.array([*offset, 0.0])
            camera = camera_for("mouth", mouth, scene.world.points(), task.config.world.depth)
            _, segmentation = scene.photograph(camera, 120, 90)
            seen[view] = int(scene.peg_mask(segmentation).sum())
        finally:
            scene.close()
    assert seen["mouth"] > 1.3 * seen["wide"] > 0, seen


def _stripped(urdf: str, keep: str) -> str:
    """``urdf`` without any <visual> and without <collision> except on the link ``keep``."""
    text = re.sub(r"<visual>.*?</visual>", "", Path(urdf).read_text(), flags=re.S)
    links = re.split(r"(?=<link )", text)
    return "".join(
        part if part.startswith(f'<link name="{keep}"')
        else re.sub(r"<collision>.*?</collision>", "", part, flags=re.S)
        for part in links
    )  # fmt: skip


def test_an_arm_without_shapes_is_drawn_as_capsules(tmp_path: Path) -> None:
    urdf = tmp_path / "bare.urdf"
    urdf.write_text(_stripped(KUKA, keep="peg"))
    arm = load_arm(str(urdf), None, PegConfig())
    scene = Scene(arm, WorldConfig(), (0.6, 0.0, 0.2), "wide")
    try:
        bodies = {part.body for part in scene.display.parts if part.parent is not None}
        assert len(bodies) >= arm.dof  # a capsule per moving link at least
        camera = scene.camera((0.0, 0.0), np.zeros(arm.dof))  # upright, the peg on top
        rgb, segmentation = scene.photograph(camera, 160, 120)
        peg = scene.peg_mask(segmentation)
    finally:
        scene.close()
    assert peg.sum() > 20  # no capsule hides the peg (its tip frame gets none)
    drawn = np.isin(segmentation & ((1 << 24) - 1), list(bodies))
    assert drawn.sum() > 100
    shade = rgb[drawn].astype(float).mean(axis=0) / 255
    assert np.allclose(shade / shade.max(), np.asarray(BARE_ARM[:3]) / max(BARE_ARM[:3]), atol=0.1)


def test_bad_options_are_one_error_line(
    tiny_run: LoadedRun, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(LolgpsError, match="no completed condition"):
        parse_conditions("0,5", [0, 1])
    with pytest.raises(LolgpsError, match="size"):
        replace(RenderConfig(), size=(95, 64))
    assert parse_conditions("all", [0, 1]) == [0, 1] and asdict(RenderConfig())["who"] == "policy"
    run = str(tiny_run.folder.path)
    for argv in (["--out", "clip.avi"], ["--conditions", "3"], ["--after", "7", "--out", "a.gif"]):
        monkeypatch.setattr(sys, "argv", ["render.py", "--run", run, *argv])
        with pytest.raises(SystemExit) as exit_info:
            runpy.run_path(str(SCRIPT), run_name="__main__")
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err
