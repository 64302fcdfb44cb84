"""Videos of noiseless rollouts: the global policy or the local controllers at a run's
training positions, filmed in a display scene (``scene.py``: the arm, the hole, the camera
and the captions) and encoded as ``.mp4`` or ``.gif``.

The rollouts run once, through the task's own sampler: the policy's as one batch, each local
controller's ``u_t = K_t x_t + k_t`` alone, as the stream measures them, so a clip's final
distance is the one ``summary.json`` records (``policy_final_distance_end`` for the final
policy; ``local_final_distance`` for the replay's p_cur, which labelled D_g). The display
:class:`~lolgps_torch.evaluation.scene.Scene` is then posed from the recorded joint angles
``q_t`` of every ``every``-th state and photographed by a camera fixed per clip.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import torch
from PIL import Image

from lolgps_torch.data.run_folder import atomic_write
from lolgps_torch.errors import LolgpsError, check_fields
from lolgps_torch.evaluation.scene import Clip, Scene, View, caption
from lolgps_torch.lolgps.run import LoadedRun
from lolgps_torch.policy.actor import controller_actor, policy_actor
from lolgps_torch.sim.franka import SIMULATED, RealArmConfig
from lolgps_torch.task import PegTask

Who = Literal["policy", "controller", "both"]
Layout = Literal["grid", "sequence"]
FORMATS = (".mp4", ".gif")


@dataclass(frozen=True)
class RenderConfig:
    """What to film and how.

    :param who: the global policy's rollouts, the local controllers', or both side by side.
    :param view: wide (the hole and the peg's start) or mouth (a close-up of the funnel,
        cut open on the camera's side).
    :param layout: clips side by side in a grid, or one after another.
    :param size: width and height of one clip (pixels, even).
    :param fps: frames per second of the video.
    :param every: film every k-th control step (and always the last state).
    :param columns: clips per row of the grid.
    """

    who: Who = "policy"
    view: View = "wide"
    layout: Layout = "grid"
    size: tuple[int, ...] = (240, 180)
    fps: float = 20.0
    every: int = 1
    columns: int = 4

    def __post_init__(self) -> None:
        for name, kind in (("who", Who), ("view", View), ("layout", Layout)):
            if getattr(self, name) not in get_args(kind):
                raise LolgpsError(f"{name} {getattr(self, name)!r}: one of {get_args(kind)}")
        check_fields(
            self,
            {
                "size": len(self.size) == 2
                and all(32 <= s <= 4096 and s % 2 == 0 for s in self.size),
                "fps": 0.0 < self.fps <= 120.0,
                "every": self.every >= 1,
                "columns": self.columns >= 1,
            },
        )


def parse_conditions(text: str, available: Sequence[int]) -> list[int]:
    """``"all"`` -> ``available``; ``"0,3"`` -> ``[0, 3]``, each one of ``available``."""
    if text == "all":
        return list(available)
    try:
        chosen = [int(part) for part in text.split(",")]
    except ValueError:
        raise LolgpsError(f"--conditions {text!r}: 'all' or a comma-separated list") from None
    missing = sorted(set(chosen) - set(available))
    if missing:
        raise LolgpsError(
            f"--conditions {text}: the run has no completed condition {missing} "
            f"(completed: {list(available)})"
        )
    return chosen


def check_output(path: str | Path) -> Path:
    """``path`` as a video file this module writes: ``.mp4`` (needs imageio-ffmpeg, which
    ships ffmpeg in its wheel: the ``video`` extra) or ``.gif`` (Pillow); anything else is a
    :class:`LolgpsError`."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise LolgpsError(f"--out {path}: the video must end in {' or '.join(FORMATS)}")
    if path.suffix.lower() == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise LolgpsError(
                "an .mp4 needs imageio-ffmpeg (pip install -e '.[video]'); a .gif does not"
            ) from None
    return path


def record_clips(
    loaded: LoadedRun,
    task: PegTask,
    conditions: Sequence[int],
    who: Who,
    after: int | None = None,
) -> list[Clip]:
    """The noiseless rollouts to film at ``conditions``: the global policy's checkpointed
    after condition ``after`` (default the last; one batch) and/or each condition's final
    local controller p_cur (from the replay)."""
    records = {r.condition: r for r in loaded.records}
    offsets = [records[c].offset for c in conditions]
    clips: dict[tuple[str, int], Clip] = {}
    if who in ("policy", "both"):
        x = task.sampler.rollout(policy_actor(loaded.policy(after), task.model), offsets).x
        for c, off, xs in zip(conditions, offsets, x, strict=True):
            clips["policy", c] = _clip(task, "policy", c, off, xs)
    if who in ("controller", "both"):
        zero = torch.zeros(1, task.T, task.layout.dU, dtype=torch.float64, device=task.device)
        limits = loaded.policy(after).config.limits()  # the run's, as its samples had them
        for c, off in zip(conditions, offsets, strict=True):
            p_cur = records[c].p_cur
            if p_cur is None:
                raise LolgpsError(f"{loaded.folder.replay_path}: condition {c} stores no p_cur")
            x = task.sampler.rollout(controller_actor(p_cur, zero, task.model, limits), [off]).x
            clips["controller", c] = _clip(task, "controller", c, off, x[0])
    kinds = ("policy", "controller") if who == "both" else (who,)
    return [clips[kind, c] for c in conditions for kind in kinds]


def _clip(
    task: PegTask,
    who: Literal["policy", "controller"],
    condition: int,
    offset: tuple[float, float],
    x: torch.Tensor,
) -> Clip:
    """A :class:`Clip` of the states ``x: [T+1, dX]`` of one rollout."""
    layout = task.layout
    distance = x[:, layout.points][:, :3].norm(dim=-1).cpu().numpy()
    success = bool(distance[-1] < task.config.world.success_threshold)
    return Clip(who, condition, offset, x[:, layout.q].cpu().numpy(), distance, success)


def frame_steps(T: int, every: int) -> list[int]:
    """The states filmed: ``0, every, 2 every, ...`` and the last one, ``T``."""
    steps = list(range(0, T + 1, every))
    return steps if steps[-1] == T else [*steps, T]


def film(
    scene: Scene, clips: Sequence[Clip], config: RenderConfig, dt: float
) -> Iterator[np.ndarray]:
    """The video's frames, ``[H, W, 3]`` uint8: the clips tiled ``columns`` to a row (grid,
    every clip at the same step; the shorter wait on their last frame) or one after another
    (sequence)."""
    W, H = config.size
    cameras = [scene.camera(clip.offset, clip.q[0]) for clip in clips]
    steps = frame_steps(len(clips[0].q) - 1, config.every)

    def cell(index: int, t: int) -> np.ndarray:
        clip = clips[index]
        scene.show(clip.offset, clip.q[t])
        rgb, _ = scene.photograph(cameras[index], W, H)
        image = Image.fromarray(rgb)
        caption(image, clip, t, dt)
        return np.asarray(image)

    if config.layout == "sequence":
        for index in range(len(clips)):
            for t in steps:
                yield cell(index, t)
        return
    columns = min(config.columns, len(clips))
    rows = -(-len(clips) // columns)
    for t in steps:
        mosaic = np.full((rows * H, columns * W, 3), 255, dtype=np.uint8)
        for index in range(len(clips)):
            r, col = divmod(index, columns)
            mosaic[r * H : (r + 1) * H, col * W : (col + 1) * W] = cell(index, t)
        yield mosaic


def frame_count(n_clips: int, T: int, config: RenderConfig) -> int:
    """How many frames :func:`film` yields."""
    per_clip = len(frame_steps(T, config.every))
    return per_clip * (n_clips if config.layout == "sequence" else 1)


def write_video(frames: Iterator[np.ndarray], path: Path, fps: float) -> int:
    """Write ``frames`` to ``path`` (``.mp4``: H.264 through imageio-ffmpeg; ``.gif``:
    Pillow, one palette per frame), atomically; returns the number of frames."""
    count = 0

    def counted() -> Iterator[np.ndarray]:
        nonlocal count
        for frame in frames:
            count += 1
            yield frame

    writer: Callable[[Path], None]
    if path.suffix.lower() == ".gif":

        def writer(tmp: Path) -> None:
            images = [Image.fromarray(f).quantize(colors=128, method=Image.Quantize.MEDIANCUT)
                      for f in counted()]  # fmt: skip
            images[0].save(
                tmp,
                format="GIF",
                save_all=True,
                append_images=images[1:],
                duration=round(1000 / fps),
                loop=0,
                optimize=False,
            )
    else:
        import imageio_ffmpeg

        def writer(tmp: Path) -> None:
            out = None
            for frame in counted():
                if out is None:
                    size = (frame.shape[1], frame.shape[0])
                    out = imageio_ffmpeg.write_frames(
                        str(tmp), size, fps=fps, codec="libx264", quality=7,
                        macro_block_size=2, output_params=["-f", "mp4"],
                    )  # fmt: skip
                    out.send(None)
                out.send(np.ascontiguousarray(frame))
            if out is not None:
                out.close()

    atomic_write(path, writer)
    return count


def render_clips(task: PegTask, clips: Sequence[Clip], config: RenderConfig, out: Path) -> None:
    """Film ``clips`` of ``task``'s arm into ``out`` (:func:`film`, :func:`write_video`)."""
    scene = Scene(task.arm, task.config.world, task.geometry.nominal_mouth, config.view)
    try:
        write_video(film(scene, clips, config, task.config.world.dt), out, config.fps)
    finally:
        scene.close()


def render_run(
    loaded: LoadedRun,
    conditions: Sequence[int],
    config: RenderConfig,
    out: Path,
    after: int | None = None,
    real: RealArmConfig = SIMULATED,
) -> list[Clip]:
    """Film the noiseless rollouts at ``conditions`` (module docstring; the policy
    checkpointed after condition ``after``, default the last) into ``out``; returns the
    clips, whose final distances the captions show. On a real arm (``real``) the rollouts
    run on it and the display replays their joint angles."""
    task = loaded.make_task(min(len(conditions), 8), real)
    try:
        clips = record_clips(loaded, task, conditions, config.who, after)
        render_clips(task, clips, config, out)
    finally:
        task.close()
    return clips
