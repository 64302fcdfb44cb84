"""Batched forward kinematics of the peg points with pytorch-kinematics (float64).

``p(q) = R(q) o + t(q)`` for each point offset ``o`` in the point frame, where ``(R, t)``
is the point frame's pose in the root link's frame; ``J = dp/dq`` is the point Jacobian.
"""

from __future__ import annotations

import contextlib
import io

import pytorch_kinematics as pk
import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import ArmSpec


class PegKinematics:
    """Peg tip and top positions ``[..., 2, 3]`` and their Jacobians ``[..., 6, n]``."""

    def __init__(self, arm: ArmSpec, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        # pytorch-kinematics reports tags it does not model (materials, contacts) on stderr
        with contextlib.redirect_stderr(io.StringIO()):
            chain = pk.build_serial_chain_from_urdf(arm.urdf_text, arm.point_link, arm.root_link)
        self.chain = chain.to(dtype=torch.float64, device=self.device)
        names = tuple(self.chain.get_joint_parameter_names())
        if names != arm.joint_names:
            raise LolgpsError(
                f"kinematic chain joints {names} differ from the arm's {arm.joint_names}"
            )
        self.offsets = torch.tensor(arm.point_offsets, dtype=torch.float64, device=self.device)
        self.joint_frames = list(self.chain.get_joint_parent_frame_names())
        self.point_frame = arm.point_link
        # joint axes in their own (child link) frames, [n, 3]
        self.axes = torch.stack([self.chain.find_frame(f).joint.axis for f in self.joint_frames])

    def points(self, q: Tensor) -> Tensor:
        """World positions of the tip and top points, ``q: [..., n] -> [..., 2, 3]``."""
        batch = q.shape[:-1]
        m = self.chain.forward_kinematics(q.reshape(-1, q.shape[-1])).get_matrix()  # [B, 4, 4]
        pts = torch.einsum("bij,pj->bpi", m[:, :3, :3], self.offsets) + m[:, None, :3, 3]
        return pts.reshape(*batch, 2, 3)

    def jacobian(self, q: Tensor) -> Tensor:
        """Stacked point Jacobians ``d[p_tip; p_top]/dq``, ``q: [..., n] -> [..., 6, n]``."""
        return self.points_and_jacobian(q)[1]

    def points_and_jacobian(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Points ``[..., 2, 3]`` and Jacobians ``[..., 6, n]`` from one kinematics pass.

        For revolute joint i with world axis w_i and origin o_i: dp/dq_i = w_i x (p - o_i).
        """
        batch, n = q.shape[:-1], q.shape[-1]
        frames = self.chain.forward_kinematics(q.reshape(-1, n), end_only=False)
        m = frames[self.point_frame].get_matrix()  # [B, 4, 4]
        pts = torch.einsum("bij,pj->bpi", m[:, :3, :3], self.offsets) + m[:, None, :3, 3]
        joints = torch.stack([frames[f].get_matrix() for f in self.joint_frames], 1)  # [B, n, 4, 4]
        w = torch.einsum("bnij,nj->bni", joints[..., :3, :3], self.axes)  # [B, n, 3]
        r = pts[:, :, None, :] - joints[:, None, :, :3, 3]  # [B, 2, n, 3]
        J = torch.linalg.cross(w[:, None].expand_as(r), r)  # [B, 2, n, 3]
        return pts.reshape(*batch, 2, 3), J.permute(0, 1, 3, 2).reshape(*batch, 6, n)
