"""What a video's frame shows: a :class:`Scene`, the simulator seam's display of the run's arm
and a coloured copy of its hole (:func:`~lolgps_torch.sim.engines.build_display`), posed
from a :class:`Clip`'s recorded joint angles and photographed by a camera fixed per clip,
and the :func:`caption` drawn on it. No physics runs in the display. ``render.py`` records
the clips and encodes the frames into a video.

Views: ``wide`` frames the hole and the peg's start; ``mouth`` is a close-up of the funnel,
cut open on the camera's side (the hole's shapes on that side are not drawn) so the peg can be
seen passing the mouth, where the clearance per side is ``clearance_mouth`` (4 mm by default).
"""

from __future__ import annotations

import functools
import math
from typing import Literal, NamedTuple

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.engines import build_display
from lolgps_torch.sim.simulator import Camera, Display, WorldConfig

View = Literal["wide", "mouth"]

SUCCESS, MISS = (40, 160, 70), (200, 50, 40)


class Clip(NamedTuple):
    """One noiseless rollout to film: who acted, at which condition and hole offset (m), the
    recorded joint angles ``q: [T+1, n]`` (``q_T`` after the last action), the tip's distance
    to its target at every state ``[T+1]`` (m), and whether the final one is below the success
    threshold."""

    who: Literal["policy", "controller"]
    condition: int
    offset: tuple[float, float]
    q: np.ndarray
    distance: np.ndarray
    success: bool

    @property
    def final_distance(self) -> float:
        return float(self.distance[-1])


# From the target towards the camera: from the front and the arm's right, above, looking at
# the arm's reach (+x) across.
_WIDE_FROM = np.array([0.35, -1.0, 0.65])
_MOUTH_FROM = np.array([0.25, -1.0, 0.6])


def camera_for(view: View, mouth: np.ndarray, start: np.ndarray, depth: float) -> Camera:
    """The camera of one clip. wide: a 40 degree view, from ``_WIDE_FROM``, of the sphere
    around the hole's mouth and the peg's tip and top points at the start (``start: [2, 3]``)
    with a 6 cm margin; mouth: a 30 degree view of the funnel's upper half (``depth`` its
    depth), from ``_MOUTH_FROM``."""
    if view == "wide":
        points = np.vstack([mouth, start])
        target = (points.min(axis=0) + points.max(axis=0)) / 2
        radius = float(np.linalg.norm(points - target, axis=1).max()) + 0.06
        fov, direction = 40.0, _WIDE_FROM
    else:
        target = mouth - np.array([0.0, 0.0, 0.3 * depth])
        radius, fov, direction = 0.9 * depth, 30.0, _MOUTH_FROM
    distance = radius / math.sin(math.radians(fov / 2))
    return Camera(target + distance * direction / np.linalg.norm(direction), target, fov)


class Scene:
    """The display of the run's arm and hole (the simulator seam's :class:`Display`) and the
    cameras of a view.

    :param arm: the run's arm. :param config: its world settings.
    :param nominal_mouth: the hole's mouth at offset zero (world, m).
    :param view: the camera's view; ``mouth`` leaves out the hole's shapes on its side.
    """

    def __init__(
        self, arm: ArmSpec, config: WorldConfig, nominal_mouth: tuple[float, ...], view: View
    ) -> None:
        cut = _MOUTH_FROM[:2] / np.linalg.norm(_MOUTH_FROM[:2]) if view == "mouth" else None
        self.display: Display = build_display(arm, config, nominal_mouth, cut)
        self.world, self.view, self.depth = self.display.world, view, config.depth

    def show(self, offset: tuple[float, float], q: np.ndarray) -> None:
        """Put the hole at ``offset`` and the arm at joint angles ``q``, at rest."""
        self.display.show(offset, q)

    def camera(self, offset: tuple[float, float], q0: np.ndarray) -> Camera:
        """The fixed camera of a clip at ``offset`` whose arm starts at ``q0``."""
        self.display.show(offset, q0)
        mouth = self.world.nominal_mouth + np.array([*offset, 0.0])
        return camera_for(self.view, mouth, self.world.points(), self.depth)

    def photograph(self, camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The current pose through ``camera``: RGB ``[H, W, 3]`` uint8 on a plain background, and the
        segmentation ``[H, W]`` that :meth:`peg_mask` reads."""
        return self.display.photograph(camera, width, height)

    def peg_mask(self, segmentation: np.ndarray) -> np.ndarray:
        """Where a segmentation of :meth:`photograph` shows the peg, ``[H, W]`` bool."""
        return self.display.peg_mask(segmentation)

    def close(self) -> None:
        self.display.close()


@functools.cache
def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    return ImageFont.load_default(size=size)


def caption(image: Image.Image, clip: Clip, t: int, dt: float) -> None:
    """Draw on a clip's frame: who, condition and hole offset (top); time, step and the tip's
    distance now (bottom left); the clip's outcome, success or miss at its final distance
    (bottom right)."""
    draw = ImageDraw.Draw(image, "RGBA")
    W, H = image.size
    size = max(9, H // 15)
    font, strip = _font(size), size + 6
    draw.rectangle((0, 0, W, strip), fill=(0, 0, 0, 140))
    draw.rectangle((0, H - strip, W, H), fill=(0, 0, 0, 140))
    dx, dy = (1000 * v for v in clip.offset)
    top = f"{clip.who} · condition {clip.condition} · hole {dx:+.0f}, {dy:+.0f} mm"
    draw.text((4, 3), top, fill="white", font=font)
    now = f"t {t * dt:4.2f} s ({t})  tip {1000 * clip.distance[t]:5.1f} mm"
    draw.text((4, H - strip + 3), now, fill="white", font=font)
    outcome = f"{'success' if clip.success else 'miss'} {1000 * clip.final_distance:.0f} mm"
    box = draw.textbbox((0, 0), outcome, font=font)
    x0 = W - (box[2] - box[0]) - 8
    draw.rectangle((x0 - 2, H - strip, W, H), fill=SUCCESS if clip.success else MISS)
    draw.text((x0 + 2, H - strip + 3), outcome, fill="white", font=font)
