"""Joint-space rigid-body dynamics of an arm's chain, in torch (float64, batched, differentiable).

The equation of motion of the actuated joints ``q: [..., n]`` is

    ``M(q) qdd + c(q, qd) + g(q) = tau + tau_ext``

with the mass matrix M, the Coriolis and centrifugal torques c, the gravity torques g and the
generalised force ``tau_ext = sum_b S_b^T w_b`` of external wrenches ``w_b`` on the bodies.

The chain is the path of the :class:`~lolgps_torch.robot.spec.ArmSpec`'s URDF from its root
link to the point frame. Body k is the child link of the k-th actuated joint together with
everything rigidly attached to it: the links below it through fixed joints, through *locked*
joints (moving joints that are not actuated, held at a given position: gripper fingers,
mimic joints) and the attached peg. Links attached to the root do not move and are dropped.

Everything is computed in the world (root) frame with spatial vectors at the world origin,
``V = (omega, v_O)`` (v_O the velocity of the body point passing through the origin):

* joint axes ``S_k = (a_k, p_k x a_k)`` (revolute), ``(0, a_k)`` (prismatic), with a_k the
  world axis and p_k the origin of joint k;
* inverse dynamics by the recursive Newton-Euler algorithm, whose forward recursion is a
  cumulative sum in this frame:
  ``V_k = sum_{j<=k} S_j qd_j``, ``A_k = A_0 + sum_{j<=k} (S_j qdd_j + V_j x S_j qd_j)``,
  ``A_0 = (0, -g_vec)`` (gravity as a base acceleration), body wrenches
  ``f_k = I_k A_k + V_k x* I_k V_k - w_k``, ``F_k = sum_{j>=k} f_j``, ``tau_k = S_k . F_k``;
* the mass matrix by the composite-rigid-body algorithm:
  ``M_jk = S_j . (sum_{i>=k} I_i) S_k`` for ``j <= k``;
* forward dynamics ``qdd = M^{-1} (tau + tau_ext - c - g)`` by a Cholesky solve.

A body's spatial inertia at the origin, from its mass m, first moment ``h = m c`` and
rotational inertia ``J = I_c - m [c]x^2`` about the origin, maps a twist to a momentum:
``I (omega, v) = (J omega + h x v, m v - h x omega)``.

Inertias.  ``inertia="urdf"`` takes the URDF's inertia tensors as written (as Pinocchio does).
``inertia="pybullet"`` takes them as PyBullet loads them with ``URDF_USE_INERTIA_FROM_FILE``:
a link whose principal moments break the triangle inequality gets zero rotational inertia
(PyBullet warns and zeroes it; pybullet_data's xArm 6 has such links).

Why this module is longer than 450 lines: it is one chain's RNEA, CRBA and forward dynamics
with their derivatives, kept together. Its URDF reading builds exactly the bodies and joint
transforms those recursions run on, and its small spatial-algebra helpers serve nothing else.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.spec import ArmSpec

InertiaSource = Literal["urdf", "pybullet"]
_MOVING = ("revolute", "continuous", "prismatic")
# |v| is taken as sqrt(|v|^2 + _NORM_FLOOR^2), so its derivative is defined at v = 0.
_NORM_FLOOR = 1e-12


class _Joint(NamedTuple):
    name: str
    kind: str
    parent: str
    child: str
    origin: Tensor  # [4, 4] parent link -> joint frame at q = 0
    axis: Tensor  # [3] unit axis in the joint frame
    damping: float


class _Link(NamedTuple):
    mass: float
    com: Tensor  # [3] centre of mass in the link frame
    inertia: Tensor  # [3, 3] rotational inertia about the COM, link axes


class Frames(NamedTuple):
    """World poses of the bodies at ``q: [..., n]``: rotations ``R: [..., n, 3, 3]`` and
    origins ``p: [..., n, 3]`` (the child frame of each actuated joint)."""

    R: Tensor
    p: Tensor


@dataclass(frozen=True)
class BodyParameters:
    """Inertial parameters of the n bodies and their S sub-links, in the body frames.

    :param mass: body masses ``[n]``. :param first_moment: ``m c`` per body ``[n, 3]``.
    :param inertia: rotational inertia about the body origin ``[n, 3, 3]``.
    :param link_body: the body each sub-link belongs to ``[S]`` (int64).
    :param link_mass: ``[S]``. :param link_com: sub-link COMs in their body's frame ``[S, 3]``.
    :param link_inertia: sub-link inertias about their COMs, body axes ``[S, 3, 3]``.
    """

    mass: Tensor
    first_moment: Tensor
    inertia: Tensor
    link_body: Tensor
    link_mass: Tensor
    link_com: Tensor
    link_inertia: Tensor


class ArmDynamics:
    """Rigid-body dynamics of the actuated chain of an :class:`ArmSpec` (see the module docstring).

    :param arm: the parsed arm; its ``urdf_text`` (peg attached) is the one PyBullet loads.
    :param gravity: gravitational acceleration (m/s^2) along -z of the root frame.
    :param inertia: ``"urdf"`` or ``"pybullet"`` (see the module docstring).
    :param locked: positions of moving joints that are not actuated (default 0, the position
        PyBullet loads them at); unnamed ones are held at 0.
    :param rotor_inertia: per actuated joint, an isotropic inertia (kg m^2) added to its child
        link, as :class:`~lolgps_torch.sim.world.PegWorld` adds where joint damping would be
        unstable (None: none).
    :param device: where the tensors live.
    """

    def __init__(
        self,
        arm: ArmSpec,
        gravity: float = 9.81,
        inertia: InertiaSource = "urdf",
        locked: Mapping[str, float] | None = None,
        rotor_inertia: Sequence[float] | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        if inertia not in ("urdf", "pybullet"):
            raise LolgpsError(f"inertia must be 'urdf' or 'pybullet', got {inertia!r}")
        self.arm, self.inertia_source, self.gravity = arm, inertia, float(gravity)
        self.device = torch.device(device)
        self.n = arm.dof
        links, joints = _parse(arm.urdf_text)
        chain = _chain(joints, arm.root_link, arm.point_link)
        actuated = [j for j in chain if j.name in arm.joint_names]
        if tuple(j.name for j in actuated) != arm.joint_names:
            raise LolgpsError(
                f"the chain to {arm.point_link!r} has actuated joints "
                f"{[j.name for j in actuated]}, the arm {list(arm.joint_names)}"
            )
        locked = dict(locked or {})
        # Pose of every link in the frame of the body it belongs to (None: the static root).
        body_of: dict[str, int | None] = {arm.root_link: None}
        pose: dict[str, Tensor] = {arm.root_link: torch.eye(4, dtype=torch.float64)}
        tree_origin, axes, kinds = [], [], []
        for joint in chain:
            if joint.name in arm.joint_names:
                tree_origin.append(pose[joint.parent] @ joint.origin)
                axes.append(joint.axis)
                kinds.append(joint.kind)
                body_of[joint.child] = len(axes) - 1
                pose[joint.child] = torch.eye(4, dtype=torch.float64)
            else:
                body_of[joint.child] = body_of[joint.parent]
                pose[joint.child] = pose[joint.parent] @ _joint_transform(joint, locked)
        self._attach_branches(joints, body_of, pose, locked)
        self.joint_damping = torch.tensor(
            [j.damping for j in actuated], dtype=torch.float64, device=self.device
        )
        origin = torch.stack(tree_origin)  # [n, 4, 4], body k-1 (or root) -> joint k frame
        self._tree_p = origin[:, :3, 3].to(self.device)
        self._axes = torch.stack(axes).to(self.device)  # [n, 3]
        self._kinds = tuple("prismatic" if k == "prismatic" else "revolute" for k in kinds)
        self._prismatic = torch.tensor([k == "prismatic" for k in kinds], device=self.device)
        # Rodrigues with the tree rotation E folded in: E R(a, q) = E + sin q E K + (1 - cos q) E K^2
        E, K = origin[:, :3, :3], _skew(torch.stack(axes))
        self._tree_R = tuple(r.to(self.device) for r in (E, E @ K, E @ K @ K))
        point = pose[arm.point_link]
        if body_of[arm.point_link] != self.n - 1:
            raise LolgpsError(f"the point frame {arm.point_link!r} is not on the last body")
        self._point_R = point[:3, :3].to(self.device)
        self._point_p = point[:3, 3].to(self.device)
        self.offsets = torch.tensor(arm.point_offsets, dtype=torch.float64, device=self.device)
        rotor = [0.0] * self.n if rotor_inertia is None else list(rotor_inertia)
        if len(rotor) != self.n or min(rotor) < 0.0:
            raise LolgpsError(f"rotor_inertia needs {self.n} values >= 0, got {rotor}")
        self.rotor_inertia = tuple(float(r) for r in rotor)
        self.body = self._body_parameters(links, body_of, pose, actuated)

    def _attach_branches(
        self,
        joints: dict[str, _Joint],
        body_of: dict[str, int | None],
        pose: dict[str, Tensor],
        locked: Mapping[str, float],
    ) -> None:
        """Give every link off the chain the body and pose of its nearest chain ancestor."""
        pending = [j for j in joints.values() if j.child not in body_of]
        while pending:
            ready = [j for j in pending if j.parent in body_of]
            if not ready:
                raise LolgpsError("links off the chain are not connected to it")
            for joint in ready:
                body_of[joint.child] = body_of[joint.parent]
                pose[joint.child] = pose[joint.parent] @ _joint_transform(joint, locked)
            pending = [j for j in pending if j.child not in body_of]

    def _body_parameters(
        self,
        links: dict[str, _Link],
        body_of: dict[str, int | None],
        pose: dict[str, Tensor],
        actuated: list[_Joint],
    ) -> BodyParameters:
        rotor = {j.child: r for j, r in zip(actuated, self.rotor_inertia, strict=True)}
        index, masses, coms, inertias = [], [], [], []
        for name, body in body_of.items():
            if body is None:
                continue
            link = links[name]
            inertia = link.inertia
            if self.inertia_source == "pybullet":
                inertia = _pybullet_inertia(inertia)
            inertia = inertia + rotor.get(name, 0.0) * torch.eye(3, dtype=torch.float64)
            R, t = pose[name][:3, :3], pose[name][:3, 3]
            index.append(body)
            masses.append(link.mass)
            coms.append(R @ link.com + t)
            inertias.append(R @ inertia @ R.T)
        link_body = torch.tensor(index)
        link_mass = torch.tensor(masses, dtype=torch.float64)
        link_com, link_inertia = torch.stack(coms), torch.stack(inertias)
        one_hot = torch.nn.functional.one_hot(link_body, self.n).to(torch.float64).T  # [n, S]
        about_origin = link_inertia - link_mass[:, None, None] * _skew(link_com) @ _skew(link_com)
        params = BodyParameters(
            mass=one_hot @ link_mass,
            first_moment=one_hot @ (link_mass[:, None] * link_com),
            inertia=torch.einsum("bs,sij->bij", one_hot, about_origin),
            link_body=link_body,
            link_mass=link_mass,
            link_com=link_com,
            link_inertia=link_inertia,
        )
        return BodyParameters(
            *(getattr(params, f).to(self.device) for f in params.__dataclass_fields__)
        )

    def with_parameters(self, body: BodyParameters, joint_damping: Tensor) -> ArmDynamics:
        """The same chain with other inertial parameters and joint damping (a new instance;
        tensors may carry gradients to the parameters they were made from)."""
        other = copy.copy(self)
        other.body, other.joint_damping = body, joint_damping
        return other

    def frames(self, q: Tensor) -> Frames:
        """World rotation and origin of each body, ``q: [..., n]``:
        ``T_k = T_{k-1} X_k J_k(q_k)`` with X_k the fixed tree transform, J_k the joint motion."""
        E, EK, EK2 = self._tree_R
        sin, cos = torch.sin(q)[..., None, None], torch.cos(q)[..., None, None]  # [..., n, 1, 1]
        R_prev: Tensor | None = None
        p_prev = q.new_zeros(*q.shape[:-1], 3)
        Rs, ps = [], []
        for k, kind in enumerate(self._kinds):
            local = (
                E[k]
                if kind == "prismatic"
                else E[k] + sin[..., k, :, :] * EK[k] + (1 - cos[..., k, :, :]) * EK2[k]
            )
            R = local.expand(*q.shape[:-1], 3, 3) if R_prev is None else _mm(R_prev, local)
            p = p_prev + (self._tree_p[k] if R_prev is None else _mv(R_prev, self._tree_p[k]))
            if kind == "prismatic":
                p = p + _mv(R, self._axes[k]) * q[..., k, None]
            Rs.append(R)
            ps.append(p)
            R_prev, p_prev = R, p
        return Frames(torch.stack(Rs, -3), torch.stack(ps, -2))

    def motion_subspace(self, frames: Frames) -> Tensor:
        """World joint axes as spatial motions ``S: [..., n, 6]`` (angular, linear at O)."""
        a = _mv(frames.R, self._axes)  # [..., n, 3]
        prismatic = self._prismatic[:, None]
        angular = torch.where(prismatic, torch.zeros_like(a), a)
        linear = torch.where(prismatic, a, _cross(frames.p, a))
        return torch.cat([angular, linear], -1)

    def world_inertia(self, frames: Frames) -> tuple[Tensor, Tensor, Tensor]:
        """Body mass ``[n]``, first moment ``h = m c: [..., n, 3]`` and rotational inertia about
        the world origin ``J: [..., n, 3, 3]``; with ``y = R h_body``, ``h = m p + y`` and
        ``J = R J_body R^T - m [p]x^2 - [p]x [y]x - [y]x [p]x``
        ``  = R J_body R^T + (m |p|^2 + 2 p.y) 1 - m p p^T - p y^T - y p^T``."""
        m, p = self.body.mass, frames.p
        y = _mv(frames.R, self.body.first_moment)
        J = _mm(_mm(frames.R, self.body.inertia), frames.R.mT)
        trace = m * p.square().sum(-1) + 2 * (p * y).sum(-1)  # [..., n]
        outer = (m[:, None] * p + y)[..., :, None] * p[..., None, :] + p[..., :, None] * y[
            ..., None, :
        ]
        J = J + trace[..., None, None] * torch.eye(3, dtype=p.dtype, device=p.device) - outer
        return m, m[:, None] * p + y, J

    def inverse_dynamics(
        self, q: Tensor, qd: Tensor, qdd: Tensor, wrench: Tensor | None = None
    ) -> Tensor:
        """``tau = M(q) qdd + c(q, qd) + g(q) - tau_ext`` by the RNEA, ``[..., n]``.

        :param wrench: external wrenches on the bodies, world frame at the origin,
            ``[..., n, 6]`` (moment, force), or None.
        """
        return self.inverse_dynamics_at(self.frames(q), qd, qdd, wrench)

    def inverse_dynamics_at(
        self, frames: Frames, qd: Tensor, qdd: Tensor, wrench: Tensor | None = None
    ) -> Tensor:
        """:meth:`inverse_dynamics` at already computed :meth:`frames`."""
        return self._rnea(frames, self.motion_subspace(frames), qd, qdd, wrench)

    def _rnea(
        self, frames: Frames, S: Tensor, qd: Tensor, qdd: Tensor, wrench: Tensor | None
    ) -> Tensor:
        m, h, J = self.world_inertia(frames)
        Sqd = S * qd[..., None]  # [..., n, 6]
        V = torch.cumsum(Sqd, -2)
        A0 = S.new_zeros(6)
        A0[5] = self.gravity
        A = A0 + torch.cumsum(S * qdd[..., None] + _cross_motion(V, Sqd), -2)
        f = _apply_inertia(m, h, J, A) + _cross_force(V, _apply_inertia(m, h, J, V))
        if wrench is not None:
            f = f - wrench
        F = f.flip(-2).cumsum(-2).flip(-2)
        return (S * F).sum(-1)

    def inverse_dynamics_derivatives(
        self,
        frames: Frames,
        qd: Tensor,
        qdd: Tensor,
        wrench: Tensor | None = None,
        wrench_jacobian: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``dtau/dq``, ``dtau/dqd`` and ``dtau/dqdd = M: [..., n, n]`` of
        :meth:`inverse_dynamics_at` (the RNEA), analytically, in O(n) spatial products and
        n x n dot products.

        Moving joint k moves every body i >= k rigidly by the motion ``S_k``: its axis and
        inertia change by ``S_k x S_i`` and ``S_k x* I_i - I_i S_k x``. With ``V'_k = V_{k-1}``,
        ``A'_k = A_{k-1}`` (``A_0`` gravity), what does not follow rigidly is
        ``dV_i/dq_k - S_k x V_i = c_k = -S_k x V'_k`` and
        ``dA_i/dq_k - S_k x A_i = c_k x V_i + e_k``, ``e_k = -c_k x V'_k - S_k x A'_k``, so that
        for i >= k (nothing changes for i < k)

            ``df_i/dq_k = S_k x* f_i + I_i e_k + Y_i c_k + c_k x* I_i V_i``,
            ``Y_i = V_i x* I_i - I_i V_i x - D_i``,

        with ``D_i = dw_i/dV_i`` the wrench's derivative. For the velocities,
        ``dV_i/dqd_k = S_k`` and ``dA_i/dqd_k = S_k x V_i + 2 c_k`` (i >= k), so
        ``df_i/dqd_k = I_i 2 c_k + Y_i S_k + S_k x* I_i V_i``. Summing over ``i >= max(j, k)``
        with the composite ``Ic_j``, ``Yc_j``, ``(IV)c_j`` (sums over i >= j), and as
        ``(S_k x S_j) . F + S_j . (S_k x* F) = 0``: for ``j >= k``

            ``dtau_j/dq_k = alpha_j . e_k + beta_j . c_k``,
            ``dtau_j/dqd_k = beta_j . S_k + alpha_j . 2 c_k``,
            ``alpha_j = Ic_j S_j``, ``beta_j = Yc_j^T S_j - S_j x* (IV)c_j``,

        and for ``j < k``, ``dtau_j/dq_k = S_j . (Ic_k e_k + Yc_k c_k + c_k x* (IV)c_k
        + S_k x* F_k)`` and ``dtau_j/dqd_k = S_j . (Yc_k S_k + Ic_k 2 c_k + S_k x* (IV)c_k)``.
        The mass matrix is ``M_kj = S_k . alpha_j`` for ``j >= k`` (the CRBA).

        :param wrench: external body wrenches ``w_i: [..., n, 6]`` as in :meth:`inverse_dynamics`,
            which must move rigidly with their bodies (frame-invariant laws, as Bullet's damping)
            and depend on q and qd only through the poses and ``V_i``.
        :param wrench_jacobian: ``D_i = dw_i / dV_i: [..., n, 6, 6]`` at fixed poses
            (:meth:`link_damping_with_jacobian`), or None for wrenches independent of velocity.
        """
        _, dq, dqd, M = self._derivatives(frames, qd, qdd, None, wrench, wrench_jacobian)
        return dq, dqd, M

    def forward_dynamics_derivatives(
        self,
        frames: Frames,
        qd: Tensor,
        tau: Tensor,
        wrench: Tensor | None = None,
        wrench_jacobian: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``qdd`` of :meth:`forward_dynamics_at` and, at it, the derivatives ``dtau/dq``,
        ``dtau/dqd`` and ``M`` of :meth:`inverse_dynamics_derivatives`, from one pass over the
        chain; with them ``dqdd = M^{-1} (dtau - dtau/dq dq - dtau/dqd dqd)``."""
        qdd, dq, dqd, M = self._derivatives(frames, qd, None, tau, wrench, wrench_jacobian)
        return qdd, dq, dqd, M

    def _derivatives(
        self,
        frames: Frames,
        qd: Tensor,
        qdd: Tensor | None,
        tau: Tensor | None,
        wrench: Tensor | None,
        wrench_jacobian: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:meth:`inverse_dynamics_derivatives` at ``qdd``, or with ``qdd`` solved from ``tau``."""
        S = self.motion_subspace(frames)
        m, h, J = self.world_inertia(frames)
        Sqd = S * qd[..., None]  # [..., n, 6]
        V = torch.cumsum(Sqd, -2)
        A0 = S.new_zeros(6)
        A0[5] = self.gravity
        inertia = _inertia_matrix(m, h, J)  # [..., n, 6, 6]
        Ic = _below(inertia, -3)
        alpha = _mv(Ic, S)  # [..., j, 6]
        M = torch.triu(S @ alpha.mT)
        M = M + torch.triu(M, 1).mT
        IV = _mv(inertia, V)
        f_velocity = _cross_force(V, IV) if wrench is None else _cross_force(V, IV) - wrench
        product = _cross_motion(V, Sqd)
        if qdd is None:  # the RNEA at qdd = 0 is the bias c + g - tau_ext
            assert tau is not None
            bias = _mv(inertia, A0 + torch.cumsum(product, -2)) + f_velocity
            qdd = torch.linalg.solve(M, tau - (S * _below(bias, -2)).sum(-1))
        a = S * qdd[..., None] + product
        A = A0 + torch.cumsum(a, -2)
        V_prev, A_prev = V - Sqd, A - a  # V'_k, A'_k
        f = _mv(inertia, A) + f_velocity
        X = inertia @ _motion_cross_matrix(V)  # I_i V_i x; V_i x* I_i = -X^T
        Y = -(X + X.mT)
        if wrench_jacobian is not None:
            Y = Y - wrench_jacobian
        F, IVc, Yc = _below(f, -2), _below(IV, -2), _below(Y, -3)
        c = -_cross_motion(S, V_prev)
        e = -_cross_motion(c, V_prev) - _cross_motion(S, A_prev)
        beta = _mv(Yc.mT, S) - _cross_force(S, IVc)
        gamma_q = _mv(Ic, e) + _mv(Yc, c) + _cross_force(c, IVc) + _cross_force(S, F)  # [..., k, 6]
        gamma_qd = _mv(Yc, S) + 2 * _mv(Ic, c) + _cross_force(S, IVc)
        ones = torch.ones(self.n, self.n, dtype=torch.bool, device=S.device)
        after = torch.triu(ones)  # [k, j]: j >= k
        dq = torch.where(after, e @ alpha.mT + c @ beta.mT, gamma_q @ S.mT)  # [..., k, j]
        dqd = torch.where(after, S @ beta.mT + 2 * c @ alpha.mT, gamma_qd @ S.mT)
        return qdd, dq.mT, dqd.mT, M

    def mass_matrix(self, q: Tensor) -> Tensor:
        """``M(q): [..., n, n]`` by the composite-rigid-body algorithm."""
        frames = self.frames(q)
        return self._crba(frames, self.motion_subspace(frames))

    def _crba(self, frames: Frames, S: Tensor) -> Tensor:
        m, h, J = self.world_inertia(frames)
        # composite inertias: sums over the bodies at and below each joint
        mc = m.flip(0).cumsum(0).flip(0)
        hc = h.flip(-2).cumsum(-2).flip(-2)
        Jc = J.flip(-3).cumsum(-3).flip(-3)
        F = _apply_inertia(mc, hc, Jc, S)  # [..., n, 6], F_k = I^c_k S_k
        G = (S[..., :, None, :] * F[..., None, :, :]).sum(-1)  # [..., n, n], G_jk = S_j . F_k
        upper = torch.triu(G)
        return upper + torch.triu(G, 1).mT

    def gravity_torque(self, q: Tensor) -> Tensor:
        """``g(q) = RNEA(q, 0, 0)``, ``[..., n]``, from the bodies' first moments alone: at rest
        the RNEA's only acceleration is the upward ``a = g z`` that stands for gravity, under
        which body k (mass ``m_k``, first moment about the world origin ``h_k = m_k c_k``)
        bears the wrench ``f_k = (h_k x a, m_k a)`` at the origin, and joint j carries
        ``g_j = S_j . sum_{k >= j} f_k``. The same numbers as the full RNEA's (its other terms
        are exact zeros), in fewer operations: a world adds it to every command
        (:meth:`~lolgps_torch.sim.simulator.World.learner_compensation`)."""
        frames = self.frames(q)
        m = self.body.mass
        h = m[:, None] * frames.p + _mv(frames.R, self.body.first_moment)
        a = h.new_tensor([0.0, 0.0, self.gravity]).expand_as(h)
        f = torch.cat([_cross(h, a), m[:, None] * a], -1)  # [..., n, 6]
        F = f.flip(-2).cumsum(-2).flip(-2)
        return (self.motion_subspace(frames) * F).sum(-1)

    def forward_dynamics(
        self, q: Tensor, qd: Tensor, tau: Tensor, wrench: Tensor | None = None
    ) -> Tensor:
        """``qdd = M(q)^{-1} (tau + tau_ext - c(q, qd) - g(q))``, ``[..., n]``."""
        frames = self.frames(q)
        return self.forward_dynamics_at(frames, qd, tau, wrench)

    def forward_dynamics_at(
        self, frames: Frames, qd: Tensor, tau: Tensor, wrench: Tensor | None = None
    ) -> Tensor:
        """:meth:`forward_dynamics` at already computed :meth:`frames`."""
        S = self.motion_subspace(frames)
        bias = self._rnea(frames, S, qd, torch.zeros_like(qd), wrench)
        M = self._crba(frames, S)
        return torch.linalg.solve(M, (tau - bias)[..., None]).squeeze(-1)

    def link_damping(self, frames: Frames, qd: Tensor, linear: float, angular: float) -> Tensor:
        """Bullet's velocity damping of every link as body wrenches ``[..., n, 6]`` (world, at O).

        For a link of mass m, COM velocity v and angular velocity omega, inertia I about its
        COM: force ``-linear (1 + |v|) m v`` at the COM, moment ``-angular (1 + |omega|) I omega``
        (``btMultiBody``'s k1 + k2 |v| damping, both coefficients equal).
        """
        omega, v, com, R = self._link_motion(frames, qd)
        I_omega = _mv(R, _mv(self.body.link_inertia, _mv(R.mT, omega)))  # I_world omega
        force = -linear * (1 + _norm(v)) * self.body.link_mass[:, None] * v
        moment = -angular * (1 + _norm(omega)) * I_omega + _cross(com, force)
        return self._to_bodies(torch.cat([moment, force], -1), "...si,sb->...bi")

    def link_damping_with_jacobian(
        self, frames: Frames, qd: Tensor, linear: float, angular: float
    ) -> tuple[Tensor, Tensor]:
        """:meth:`link_damping`'s wrenches ``w_b`` and ``D_b = dw_b / dV_b: [..., n, 6, 6]``,
        their derivative with respect to the body's spatial velocity ``V_b = (omega, v_O)`` at
        fixed poses. Per link, with ``K_v = -linear m ((1 + |v|) 1 + v v^T / |v|)``,
        ``K_w = -angular ((1 + |omega|) I + I omega omega^T / |omega|)`` and ``C = [com]x``
        (``v = v_O - C omega``):

            ``D = [[K_w - C K_v C, C K_v], [-K_v C, K_v]]``, summed over the body's links.
        """
        omega, v, com, R = self._link_motion(frames, qd)
        I_world = _mm(_mm(R, self.body.link_inertia), R.mT)
        eye = torch.eye(3, dtype=qd.dtype, device=qd.device)
        speed, spin = _norm(v), _norm(omega)  # [..., S, 1]
        I_omega = _mv(I_world, omega)
        force = -linear * (1 + speed) * self.body.link_mass[:, None] * v
        moment = -angular * (1 + spin) * I_omega + _cross(com, force)
        speed, spin = speed[..., None], spin[..., None]
        K_v = (-linear * self.body.link_mass[:, None, None]) * (
            (1 + speed) * eye + v[..., :, None] * v[..., None, :] / speed
        )
        K_w = -angular * ((1 + spin) * I_world + I_omega[..., :, None] * omega[..., None, :] / spin)
        C = _skew(com)
        K_v_C = K_v @ C
        D = torch.cat([torch.cat([K_w - C @ K_v_C, C @ K_v], -1), torch.cat([-K_v_C, K_v], -1)], -2)
        wrench = self._to_bodies(torch.cat([moment, force], -1), "...si,sb->...bi")
        return wrench, self._to_bodies(D, "...sij,sb->...bij")

    def _link_motion(self, frames: Frames, qd: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per link: angular velocity, COM velocity, COM position ``[..., S, 3]`` and the
        rotation of its body ``[..., S, 3, 3]``."""
        S = self.motion_subspace(frames)
        V = torch.cumsum(S * qd[..., None], -2)  # [..., n, 6]
        b = self.body.link_body
        Vl, R, p = V[..., b, :], frames.R[..., b, :, :], frames.p[..., b, :]  # per sub-link
        omega, v_origin = Vl[..., :3], Vl[..., 3:]
        com = p + _mv(R, self.body.link_com)  # [..., S, 3]
        return omega, v_origin + _cross(omega, com), com, R

    def _to_bodies(self, per_link: Tensor, equation: str) -> Tensor:
        """Sum per-link quantities over each body's links (``equation`` contracts s)."""
        one_hot = torch.nn.functional.one_hot(self.body.link_body, self.n).to(per_link.dtype)
        return torch.einsum(equation, per_link, one_hot)

    def points(self, frames: Frames) -> Tensor:
        """World positions of the peg's tip and top, ``[..., 2, 3]``."""
        R_last, p_last = frames.R[..., -1, :, :], frames.p[..., -1, :]
        R = _mm(R_last, self._point_R)
        origin = p_last + _mv(R_last, self._point_p)
        return origin[..., None, :] + _mv(R[..., None, :, :], self.offsets)


def _parse(text: str) -> tuple[dict[str, _Link], dict[str, _Joint]]:
    """Links (inertials) and joints (by child link) of a URDF text."""
    root = ET.fromstring(text)
    links = {}
    for link in root.findall("link"):
        inertial = link.find("inertial")
        if inertial is None:
            links[link.get("name", "")] = _Link(0.0, torch.zeros(3, dtype=torch.float64),
                                                torch.zeros(3, 3, dtype=torch.float64))  # fmt: skip
            continue
        T = _origin(inertial.find("origin"))
        mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
        mass = float(mass_el.get("value", "0")) if mass_el is not None else 0.0
        value = {k: float(inertia_el.get(k, "0")) if inertia_el is not None else 0.0
                 for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}  # fmt: skip
        tensor = torch.tensor(
            [
                [value["ixx"], value["ixy"], value["ixz"]],
                [value["ixy"], value["iyy"], value["iyz"]],
                [value["ixz"], value["iyz"], value["izz"]],
            ],
            dtype=torch.float64,
        )
        R = T[:3, :3]
        links[link.get("name", "")] = _Link(mass, T[:3, 3], R @ tensor @ R.T)
    joints = {}
    for joint in root.findall("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        assert parent is not None and child is not None  # validated when the arm was loaded
        axis_el = joint.find("axis")
        axis = torch.tensor(
            _numbers(axis_el.get("xyz") if axis_el is not None else None, (1.0, 0.0, 0.0)),
            dtype=torch.float64,
        )
        dynamics = joint.find("dynamics")
        damping = float(dynamics.get("damping", "0") or 0) if dynamics is not None else 0.0
        j = _Joint(
            name=joint.get("name", ""),
            kind=joint.get("type", "fixed"),
            parent=parent.get("link", ""),
            child=child.get("link", ""),
            origin=_origin(joint.find("origin")),
            axis=axis / axis.norm(),
            damping=damping,
        )
        joints[j.child] = j
    return links, joints


def _chain(joints: dict[str, _Joint], root: str, tip: str) -> list[_Joint]:
    """The joints from ``root`` down to ``tip``; moving ones other than revolute, continuous
    and prismatic are refused."""
    chain, link = [], tip
    while link != root:
        if link not in joints:
            raise LolgpsError(f"link {tip!r} does not hang below {root!r}")
        chain.append(joints[link])
        link = joints[link].parent
    for joint in chain:
        if joint.kind not in (*_MOVING, "fixed"):
            raise LolgpsError(f"joint {joint.name!r} ({joint.kind}) is not supported on the chain")
    return chain[::-1]


def _joint_transform(joint: _Joint, locked: Mapping[str, float]) -> Tensor:
    """Parent link -> child link of a fixed joint, or of a moving one held at its lock position."""
    if joint.kind not in _MOVING:
        if joint.kind != "fixed":
            raise LolgpsError(f"joint {joint.name!r} ({joint.kind}) cannot be locked")
        return joint.origin
    value = torch.tensor(float(locked.get(joint.name, 0.0)), dtype=torch.float64)
    motion = torch.eye(4, dtype=torch.float64)
    if joint.kind == "prismatic":
        motion[:3, 3] = joint.axis * value
    else:
        motion[:3, :3] = _rotation(joint.axis, value)
    return joint.origin @ motion


def _pybullet_inertia(inertia: Tensor) -> Tensor:
    """The inertia PyBullet uses: zero if its principal moments break the triangle inequality
    (``URDF2Bullet``'s check, made on the diagonal when there are no products of inertia)."""
    off = inertia - torch.diag(torch.diagonal(inertia))
    moments = torch.diagonal(inertia) if bool((off == 0).all()) else torch.linalg.eigvalsh(inertia)
    x, y, z = (float(v) for v in moments)
    if min(x, y, z) < 0 or x > y + z or y > x + z or z > x + y:
        return torch.zeros_like(inertia)
    return inertia


def _origin(element: ET.Element | None) -> Tensor:
    """The 4x4 transform of an ``<origin xyz rpy>`` (identity when absent)."""
    T = torch.eye(4, dtype=torch.float64)
    if element is None:
        return T
    xyz = _numbers(element.get("xyz"), (0.0, 0.0, 0.0))
    r, p, y = (
        torch.tensor(v, dtype=torch.float64) for v in _numbers(element.get("rpy"), (0.0, 0.0, 0.0))
    )
    unit = torch.eye(3, dtype=torch.float64)
    T[:3, :3] = _rotation(unit[2], y) @ _rotation(unit[1], p) @ _rotation(unit[0], r)
    T[:3, 3] = torch.tensor(xyz, dtype=torch.float64)
    return T


def _numbers(text: str | None, default: tuple[float, float, float]) -> tuple[float, ...]:
    return default if not text else tuple(float(v) for v in text.split())


def _rotation(axis: Tensor, angle: Tensor) -> Tensor:
    """Rodrigues: ``R = I + sin(a) [k]x + (1 - cos(a)) [k]x^2`` for a unit axis k, ``[..., 3, 3]``."""
    K = _skew(axis).to(angle.dtype)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    eye = torch.eye(3, dtype=angle.dtype, device=angle.device)
    return eye + s * K + (1 - c) * (K @ K)


def _skew(v: Tensor) -> Tensor:
    """``[v]x: [..., 3, 3]`` with ``[v]x w = v x w``."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1),
         torch.stack([-y, x, zero], -1)], -2,
    )  # fmt: skip


def _norm(v: Tensor) -> Tensor:
    """``|v|`` over the last axis, kept, with a floor that makes it differentiable at 0."""
    return torch.sqrt(v.square().sum(-1, keepdim=True) + _NORM_FLOOR**2)


def _cross_motion(a: Tensor, b: Tensor) -> Tensor:
    """Spatial motion cross product ``(w, v) x (w2, v2) = (w x w2, w x v2 + v x w2)``."""
    w, v = a[..., :3], a[..., 3:]
    w2, v2 = b[..., :3], b[..., 3:]
    return torch.cat([_cross(w, w2), _cross(w, v2) + _cross(v, w2)], -1)


def _cross_force(a: Tensor, f: Tensor) -> Tensor:
    """Spatial force cross product ``(w, v) x* (n, f) = (w x n + v x f, w x f)``."""
    w, v = a[..., :3], a[..., 3:]
    n, force = f[..., :3], f[..., 3:]
    return torch.cat([_cross(w, n) + _cross(v, force), _cross(w, force)], -1)


def _apply_inertia(m: Tensor, h: Tensor, J: Tensor, motion: Tensor) -> Tensor:
    """``I (w, v) = (J w + h x v, m v - h x w)`` for spatial inertias (m, h, J), ``[..., 6]``."""
    w, v = motion[..., :3], motion[..., 3:]
    moment = _mv(J, w) + _cross(h, v)
    return torch.cat([moment, m[..., None] * v - _cross(h, w)], -1)


def _below(x: Tensor, dim: int) -> Tensor:
    """Sums over the bodies at and below each body: ``y_j = sum_{i>=j} x_i`` along ``dim``."""
    return x.flip(dim).cumsum(dim).flip(dim)


def _motion_cross_matrix(v: Tensor) -> Tensor:
    """``[v]x: [..., 6, 6]`` with ``[v]x X = v x X`` (:func:`_cross_motion`); ``v x* = -[v]x^T``."""
    w, lin = _skew(v[..., :3]), _skew(v[..., 3:])
    return torch.cat([torch.cat([w, torch.zeros_like(w)], -1), torch.cat([lin, w], -1)], -2)


def _inertia_matrix(m: Tensor, h: Tensor, J: Tensor) -> Tensor:
    """``[[J, [h]x], [-[h]x, m 1]]: [..., 6, 6]``, the matrix of :func:`_apply_inertia`."""
    H = _skew(h)
    mass = (m[..., None, None] * torch.eye(3, dtype=h.dtype, device=h.device)).expand(H.shape)
    return torch.cat([torch.cat([J, H], -1), torch.cat([-H, mass], -1)], -2)


def _mv(A: Tensor, v: Tensor) -> Tensor:
    """``A v`` over the last axes, ``[..., i, j] x [..., j] -> [..., i]``."""
    return torch.einsum("...ij,...j->...i", A, v)


def _mm(A: Tensor, B: Tensor) -> Tensor:
    """``A B`` over the last two axes."""
    return A @ B


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """``a x b`` over the last axis (broadcast)."""
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b)
