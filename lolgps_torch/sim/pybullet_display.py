"""The display in PyBullet: the run's arm and a coloured copy of its hole in a client of their
own, posed from joint angles and photographed with PyBullet's CPU renderer
(``ER_TINY_RENDERER``, headless).  No physics runs in it, so it draws the runs of every
simulator (:func:`~lolgps_torch.sim.engines.build_display`).

The arm is drawn from its own visual shapes (meshes or primitives). PyBullet draws a link
without one from its collision shapes; a link with neither gets a capsule from its parent's
frame to its own and a sphere at its joint, so an arm described without meshes is visible.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.pybullet_quiet import pb
from lolgps_torch.sim.simulator import Camera, WorldConfig
from lolgps_torch.sim.world import PegWorld

BACKGROUND = (222, 228, 236)
TABLE = (0.78, 0.70, 0.56, 1.0)
FUNNEL = (0.55, 0.60, 0.68, 1.0)
PEG = (0.10, 0.45, 0.90, 1.0)
BARE_ARM = (0.62, 0.64, 0.68, 1.0)  # links PyBullet draws in default white, and capsules


def camera_matrices(camera: Camera, width: int, height: int) -> tuple[list[float], list[float]]:
    """PyBullet's view and projection matrices of ``camera`` for a ``width`` x ``height``
    image."""
    view = pb.computeViewMatrix(camera.eye.tolist(), camera.target.tolist(), [0.0, 0.0, 1.0])
    distance = float(np.linalg.norm(camera.eye - camera.target))
    proj = pb.computeProjectionMatrixFOV(
        camera.fov, width / height, 0.02 * distance, 10.0 * distance
    )
    return list(view), list(proj)


class _Part(NamedTuple):
    """A visual-only body of the display drawn at ``parent``'s frame composed with the fixed
    ``local`` pose (``parent`` a link index of the arm; None for the hole's frame)."""

    body: int
    parent: int | None
    position: tuple[float, ...]
    orientation: tuple[float, ...]


class PyBulletDisplay:
    """The run's arm and a coloured copy of its hole in a PyBullet client of their own, posed
    from joint angles and photographed (module docstring; the
    :class:`~lolgps_torch.sim.simulator.Display` of the simulator seam).

    :param arm: the run's arm. :param config: its world settings.
    :param nominal_mouth: the hole's mouth at offset zero (world, m).
    :param cut: leave out the hole's boxes whose centre lies on this horizontal direction's
        side of the hole's axis (None: draw them all).
    """

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        nominal_mouth: tuple[float, ...],
        cut: np.ndarray | None,
    ) -> None:
        self.world = PegWorld(arm, config, nominal_mouth, meshes=True)
        self.client, self.cut = self.world.client, cut
        self.peg_link = self._link_index(arm.peg_link)
        self.parts = self._hole_parts() + self._arm_parts()
        # the physical hole has no visual shape (PyBullet would draw it white): out of sight
        pb.resetBasePositionAndOrientation(
            self.world.hole, [0.0, 0.0, -100.0], [0, 0, 0, 1], physicsClientId=self.client
        )
        self.offset = (0.0, 0.0)

    def _link_index(self, name: str) -> int:
        for i in range(pb.getNumJoints(self.world.body, physicsClientId=self.client)):
            if (
                pb.getJointInfo(self.world.body, i, physicsClientId=self.client)[12].decode()
                == name
            ):
                return i
        raise LolgpsError(f"the display has no link {name!r}")

    def _visual(self, **shape: object) -> int:
        kind = shape.pop("shapeType")
        visual = pb.createVisualShape(kind, physicsClientId=self.client, **shape)
        body = pb.createMultiBody(0.0, -1, visual, [0.0, 0.0, -100.0], physicsClientId=self.client)
        return int(body)

    def _hole_parts(self) -> list[_Part]:
        """One coloured box per box of the hole: the table's slabs (wider than the funnel's
        mouth by far) in TABLE, the guide plates and the floor in FUNNEL. The mouth view
        leaves out the boxes whose centre lies on the ``cut`` side of the hole's axis."""
        c, parts = self.client, []
        for shape in pb.getCollisionShapeData(self.world.hole, -1, physicsClientId=c):
            dims, position, orientation = np.asarray(shape[3]), shape[5], shape[6]
            if self.cut is not None and float(np.dot(position[:2], self.cut)) > 1e-6:
                continue
            colour = TABLE if dims[:2].max() > 10 * self.world.arm.peg_radius else FUNNEL
            body = self._visual(
                shapeType=pb.GEOM_BOX, halfExtents=(dims / 2).tolist(), rgbaColor=colour
            )
            parts.append(_Part(body, None, tuple(position), tuple(orientation)))
        return parts

    def _arm_parts(self) -> list[_Part]:
        """Colour the peg PEG and default-white links BARE_ARM; give each link that PyBullet
        draws nothing for (except the frames beyond the peg) a capsule from its parent's frame
        to its own and a sphere there."""
        c, body = self.client, self.world.body
        drawn = set()
        for shape in pb.getVisualShapeData(body, physicsClientId=c):
            link, rgba = shape[1], tuple(shape[7])
            drawn.add(link)
            if link == self.peg_link:
                pb.changeVisualShape(body, link, rgbaColor=PEG, physicsClientId=c)
            elif rgba == (1.0, 1.0, 1.0, 1.0):
                pb.changeVisualShape(body, link, rgbaColor=BARE_ARM, physicsClientId=c)
        bare = [
            j
            for j in range(pb.getNumJoints(body, physicsClientId=c))
            if j not in drawn and not self._beyond_peg(j)
        ]
        if not bare:
            return []
        self.world.reset(np.zeros(self.world.arm.dof))
        segments = {j: self._segment(j) for j in bare}
        reach = sum(float(np.linalg.norm(v)) for _, v in segments.values())
        radius = min(0.05, max(0.01, 0.04 * reach))
        return [self._capsule(j, *segments[j], radius) for j in bare]

    def _beyond_peg(self, link: int) -> bool:
        """Whether ``link`` hangs from the peg (its tip frame: the peg itself is drawn)."""
        while link != -1:
            link = pb.getJointInfo(self.world.body, link, physicsClientId=self.client)[16]
            if link == self.peg_link:
                return True
        return False

    def _frame(self, link: int | None) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """World pose of a link's frame (-1 the base), or of the hole's frame for None."""
        c, body = self.client, self.world.body
        if link is None:
            mouth = self.world.nominal_mouth + np.array([*self.offset, 0.0])
            return tuple(mouth.tolist()), (0.0, 0.0, 0.0, 1.0)
        if link == -1:
            pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=c)
            return tuple(pos), tuple(orn)
        state = pb.getLinkState(body, link, computeForwardKinematics=True, physicsClientId=c)
        return tuple(state[4]), tuple(state[5])

    def _segment(self, link: int) -> tuple[int, np.ndarray]:
        """The parent of ``link`` and the vector from the parent's frame origin to the link's
        (world, m)."""
        parent = pb.getJointInfo(self.world.body, link, physicsClientId=self.client)[16]
        return parent, np.subtract(self._frame(link)[0], self._frame(parent)[0])

    def _capsule(self, link: int, parent: int, vector: np.ndarray, radius: float) -> _Part:
        """A capsule along ``vector`` from ``parent``'s frame (a sphere if it is short), fixed
        in the parent's frame, with a sphere at its far end (the joint of ``link``)."""
        c, length = self.client, float(np.linalg.norm(vector))
        start, _ = self._frame(parent)
        axis = vector / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
        turn = np.cross([0.0, 0.0, 1.0], axis)
        angle = math.atan2(float(np.linalg.norm(turn)), float(axis[2]))
        spin = turn / np.linalg.norm(turn) if np.linalg.norm(turn) > 1e-9 else np.array([1.0, 0, 0])
        orientation = pb.getQuaternionFromAxisAngle(spin.tolist(), angle)
        shapes = [pb.GEOM_SPHERE] if length < radius else [pb.GEOM_CAPSULE, pb.GEOM_SPHERE]
        visual = pb.createVisualShapeArray(
            shapes,
            radii=[radius, 1.25 * radius][-len(shapes) :],
            lengths=[length, 0.0][-len(shapes) :],
            visualFramePositions=[[0.0, 0.0, 0.0], [0.0, 0.0, length / 2]][-len(shapes) :],
            physicsClientId=c,
        )
        body = pb.createMultiBody(0.0, -1, visual, [0.0, 0.0, -100.0], physicsClientId=c)
        pb.changeVisualShape(body, -1, rgbaColor=BARE_ARM, physicsClientId=c)
        middle = (np.asarray(start) + vector / 2).tolist()
        inverse = pb.invertTransform(*self._frame(parent))
        local = pb.multiplyTransforms(inverse[0], inverse[1], middle, orientation)
        return _Part(int(body), parent, tuple(local[0]), tuple(local[1]))

    def show(self, offset: tuple[float, float], q: np.ndarray) -> None:
        """Put the hole at ``offset`` and the arm at joint angles ``q``, at rest."""
        self.offset = offset
        self.world.reset(q)
        for part in self.parts:
            frame = self._frame(part.parent)
            pos, orn = pb.multiplyTransforms(*frame, part.position, part.orientation)
            pb.resetBasePositionAndOrientation(part.body, pos, orn, physicsClientId=self.client)

    def photograph(self, camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The current pose through ``camera``: RGB ``[H, W, 3]`` uint8 on BACKGROUND, and the
        segmentation ``[H, W]`` (``body + ((link + 1) << 24)``, -1 for the background)."""
        view, proj = camera_matrices(camera, width, height)
        _, _, rgba, _, segmentation = pb.getCameraImage(
            width,
            height,
            view,
            proj,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
            physicsClientId=self.client,
        )
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()
        seg = np.asarray(segmentation, dtype=np.int64).reshape(height, width)
        rgb[seg < 0] = BACKGROUND
        return rgb, seg

    def peg_mask(self, segmentation: np.ndarray) -> np.ndarray:
        """Where a segmentation of :meth:`photograph` shows the peg, ``[H, W]`` bool."""
        return np.asarray(segmentation == self.world.body + ((self.peg_link + 1) << 24))

    def close(self) -> None:
        self.world.close()
