"""The world's control step in free space as a differentiable torch function ``x' = f(x, u)``.

:meth:`PegWorld.step <lolgps_torch.sim.world.PegWorld.step>` holds the torque
``tau = clip(u + g(q_0), -effort, effort)`` (g the gravity compensation at the start of the
step; for an identified arm, ``κ ((1 - ρ) g_URDF + ρ g)``, g its own) for ``substeps`` physics steps of ``h = dt / substeps``. Each physics step of PyBullet's
Featherstone solver is a semi-implicit Euler step,

    ``qd <- qd + h M(q)^{-1} (tau - b qd + tau_damp(q, qd) - c(q, qd) - g(q))``,
    ``q  <- q + h qd``,

with b the URDF joint damping (applied by PyBullet at the velocity before the step) and
``tau_damp`` Bullet's link damping (:meth:`ArmDynamics.link_damping`, coefficients 0.04, the
default PyBullet leaves in place). The inertias are those PyBullet holds: the URDF's, zeroed
where the triangle inequality fails, plus the rotor-like inertia the world adds where joint
damping would be unstable (:meth:`PegWorld._stabilise_damping`, the same rule evaluated on
this model's mass matrix at q = 0).

The point features follow the state's definition (:mod:`lolgps_torch.state`): with
``P(q)`` the world positions of the tip and top,
``p' = p + P(q') - P(q)`` (the points are offsets from fixed targets) and
``v' = (P(q') - P(q)) / dt``. Contact with the table and the hole is not modelled.

With a known command delay of D physics steps (``WorldConfig.known_delay``), physics step s of
the control step t is driven by ``u_{t-j(s)}``, ``j(s) = max(0, ceil((D - s) / substeps))``,
the past actions coming from the state (:class:`~lolgps_torch.state.StateLayout`), whose
action history shifts: ``(u_{t-1}, ..., u_{t-h})' = (u_t, ..., u_{t-h+1})``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lolgps_torch.robot.rigid_body import ArmDynamics, Frames
from lolgps_torch.robot.spec import ArmSpec
from lolgps_torch.sim.simulator import WorldConfig

# btMultiBody's default linear and angular damping, which PyBullet does not change.
BULLET_LINK_DAMPING = 0.04
LINK_DAMPING = (BULLET_LINK_DAMPING, BULLET_LINK_DAMPING)  # (linear, angular)


class ControlStep:
    """``x_{t+1} = f(x_t, u_t)`` of the world in free space, batched over leading dims.

    :param arm: the parsed arm. :param config: the world's settings (dt, substeps, gravity,
        damping margin).
    :param device: where the model's tensors live.
    :param identified: the arm as identified instead of its URDF: its rigid-body model (the
        URDF's geometry) and (κ, ρ) of the gravity compensation it applies,
        ``κ ((1 - ρ) g_URDF(q) + ρ g(q))`` with g that model's own gravity torque
        (:mod:`lolgps_torch.dynamics.identify`); None: the URDF's, compensated exactly.
    """

    def __init__(
        self,
        arm: ArmSpec,
        config: WorldConfig,
        device: torch.device | str = "cpu",
        identified: tuple[ArmDynamics, float, float] | None = None,
    ) -> None:
        self.config, self.layout = config, config.layout(arm.dof)
        self.dt, self.h = config.dt, config.dt / config.substeps
        delay = config.delay_steps  # j(s): which command drives physics step s
        self.late = [max(0, -(-(delay - s) // config.substeps)) for s in range(config.substeps)]
        plain = ArmDynamics(arm, config.gravity, "pybullet", device=device)
        self.urdf = ArmDynamics(
            arm, config.gravity, "pybullet", None, stabilising_inertia(plain, config), device
        )
        self.dynamics, self.compensation, self.own = identified or (self.urdf, 1.0, 0.0)
        self.effort = torch.tensor(arm.effort, dtype=torch.float64, device=self.dynamics.device)
        #: the URDF's velocity limits and position limits ``[dU]`` (-inf/inf: a continuous joint)
        self.velocity = torch.tensor(arm.velocity, dtype=torch.float64, device=self.effort.device)
        bounded = torch.tensor(arm.bounded, device=self.effort.device)
        inf = torch.tensor(torch.inf, dtype=torch.float64, device=self.effort.device)
        self.lower = torch.where(bounded, self.effort.new_tensor(arm.lower), -inf)
        self.upper = torch.where(bounded, self.effort.new_tensor(arm.upper), inf)

    def __call__(self, x: Tensor, u: Tensor) -> Tensor:
        """The next state ``[..., dX]`` from states ``x: [..., dX]`` and actions ``u: [..., dU]``."""
        lay = self.layout
        q, qd, moved, _ = self._advance(x[..., lay.q], x[..., lay.qd], self._commands(x, u))
        return torch.cat(
            [q, qd, x[..., lay.points] + moved, moved / self.config.dt, self._shifted(x, u)], -1
        )

    def stopping(self, x: Tensor, hover: Tensor | None = None) -> Tensor:
        """The torque that stops the joints of states ``x: [n, dX]`` within one control step by
        the URDF's model, ``M(q) q-dot / dt`` (``[n, dU]``, gravity compensated, Coriolis and
        damping left out); each row computed alone, so its bits do not depend on the others.

        With ``hover = (h, tau)`` it is the torque that changes the joint speeds to ``v``
        within the step instead, ``M(q) (q-dot - v) / dt``, where ``v`` moves both peg points
        straight towards their targets raised by h (m), at 1/tau of their distance per second:

            v = J^T (J J^T + mu I)^-1 e / tau,   e = (h z - (p_tip - p*_tip), h z - (p_top - p*_top))

        with J = dP/dq the points' Jacobian (``[6, n]``), z the vertical and mu = 1e-4 m^2
        (damped least squares, bounded near singular poses)."""
        lay = self.layout
        rows = []
        for row in x:
            q, qd = row[lay.q], row[lay.qd]
            if hover is not None:
                frames = self.urdf.frames(q[None])
                raised = torch.zeros(6, dtype=x.dtype, device=x.device)
                raised[2::3] = hover[0]
                J = self._point_jacobian(frames, self.urdf.points(frames).flatten(-2))[0]
                e = raised - row[lay.points]
                JJ = J @ J.T + 1e-4 * torch.eye(6, dtype=x.dtype, device=x.device)
                qd = qd - J.T @ torch.linalg.solve(JJ, e) / hover[1]
            rows.append((self.urdf.mass_matrix(q[None])[0] * qd).sum(-1))
        return torch.stack(rows) / self.config.dt

    def mass_matrix(self, x: Tensor) -> Tensor:
        """The URDF's mass matrices ``M(q)`` at states ``x: [n, dX]`` (``[n, dU, dU]``); each
        row computed alone."""
        q = x[..., self.layout.q]
        return torch.cat([self.urdf.mass_matrix(q[i : i + 1]) for i in range(len(x))])

    def _commands(self, x: Tensor, u: Tensor) -> Tensor:
        """``[u_t, u_{t-1}, ..., u_{t-h}]: [..., h+1, dU]`` from the state's action history."""
        past = x[..., self.layout.actions].unflatten(-1, (self.layout.history, self.layout.dU))
        return torch.cat([u[..., None, :], past], -2)

    def _shifted(self, x: Tensor, u: Tensor) -> Tensor:
        """The next state's action history ``[u_t, ..., u_{t-h+1}]`` (flat)."""
        return torch.cat([u, x[..., self.layout.actions]], -1)[
            ..., : self.layout.history * self.layout.dU
        ]

    def linearize(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """``f(x, u) ~ F [x; u] + f0`` at states ``x: [B, dX]`` and actions ``u: [B, dU]``:
        ``F = df/d[x; u]: [B, dX, dX+dU]``, ``f0 = f(x, u) - F [x; u]``.

        Only q, qd and the commands (u and the past actions) move the arm, so the Jacobian of
        ``(q', qd', P(q') - P(q))`` over those inputs is propagated through the substeps
        (:meth:`_advance`); the point columns are the identity (``p' = p + ...``), the
        point-velocity columns zero, and the action history's rows a shift.
        """
        lay = self.layout
        commands = self._commands(x, u)
        q, qd, moved, J = self._advance(x[:, lay.q], x[:, lay.qd], commands, jacobian=True)
        assert J is not None
        return self.assemble(x, u, q, qd, moved, J)

    def assemble(
        self, x: Tensor, u: Tensor, q: Tensor, qd: Tensor, moved: Tensor, J: Tensor
    ) -> tuple[Tensor, Tensor]:
        """:meth:`linearize`'s ``(F, f0)`` from the joints' step at ``x: [B, dX]``,
        ``u: [B, dU]``: the next ``q, qd: [B, n]``, the points' move ``P(q') - P(q): [B, 6]``
        and the derivative ``J: [B, 2n + 6, (3 + h) n]`` of ``(q', qd', P(q') - P(q))`` with
        respect to ``(q, qd, u_t, u_{t-1}, ..., u_{t-h})``, however they were obtained."""
        lay, n = self.layout, self.layout.n_joints
        B, dX = x.shape[0], lay.dX
        F = x.new_zeros(B, dX, dX + n)
        # q, qd, u and past-action columns, in the order of _advance's inputs
        joint_cols = list(range(2 * n)) + list(range(dX, dX + n)) + list(range(dX)[lay.actions])
        F[:, : 2 * n, joint_cols] = J[:, : 2 * n]
        F[:, lay.points, joint_cols] = J[:, 2 * n :]
        F[:, lay.points, lay.points] = torch.eye(6, dtype=x.dtype, device=x.device)
        F[:, lay.point_velocities, joint_cols] = J[:, 2 * n :] / self.config.dt
        kept = lay.history * n  # u_t, u_{t-1}, ... move one place down the history
        shift_cols = list(range(dX, dX + n)) + list(range(dX)[lay.actions])
        F[:, lay.actions, shift_cols[:kept]] = torch.eye(kept, dtype=x.dtype, device=x.device)
        xu = torch.cat([x, u], -1)
        step = torch.cat(
            [q, qd, x[:, lay.points] + moved, moved / self.config.dt, self._shifted(x, u)], -1
        )
        f0 = step - (F @ xu[..., None]).squeeze(-1)
        return F, f0

    def _advance(
        self, q: Tensor, qd: Tensor, commands: Tensor, jacobian: bool = False
    ) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """Joint positions and velocities after one control step under ``commands:
        [..., h+1, n]`` (``u_t`` then the past actions), the points' move
        ``P(q') - P(q): [..., 6]`` and, if ``jacobian``, the derivative of
        ``(q', qd', P(q') - P(q))`` with respect to ``(q, qd, u_t, u_{t-1}, ..., u_{t-h})``:
        ``[..., 2n + 6, (3 + h) n]``.

        The derivative is carried forward through the substeps by the chain rule, for all
        input directions at once, from analytic derivatives of the dynamics. With ``ID(q, qd, qdd) = tau`` the inverse dynamics including both
        dampings, ``qdd = ID^{-1}(tau)`` has ``dqdd = M^{-1} (dtau - ID_q dq - ID_qd dqd)``
        (:meth:`ArmDynamics.inverse_dynamics_derivatives`); then ``dqd <- dqd + h dqdd``,
        ``dq <- dq + h dqd``. The torque held in physics step s has
        ``dtau = [clip' g_q(q_0), 0, clip' e_j(s)]`` (clip' = 1 inside the effort limits, 0
        outside; e_j the command j's columns) and a point ``P`` on the last body moves
        by ``dP/dq_k = v_k + omega_k x P`` for the joint motion ``S_k = (omega_k, v_k)``.
        """
        dyn = self.dynamics
        frames = dyn.frames(q)
        start = dyn.points(frames).flatten(-2)  # [..., 6]
        zeros = torch.zeros_like(q)
        gravity = self.compensation * self._gravity(frames, zeros)
        driving = sorted(set(self.late))
        tau = {
            j: torch.minimum(
                torch.maximum(commands[..., j, :] + gravity, -self.effort), self.effort
            )
            for j in driving
        }
        if jacobian:
            eye = torch.eye(q.shape[-1], dtype=q.dtype, device=q.device).expand(*q.shape, -1)
            none = torch.zeros_like(eye)
            gravity_q = self.urdf.inverse_dynamics_derivatives(frames, zeros, zeros)[0]
            if self.own:
                own_q = dyn.inverse_dynamics_derivatives(frames, zeros, zeros)[0]
                gravity_q = (1.0 - self.own) * gravity_q + self.own * own_q
            gravity_q = self.compensation * gravity_q
            n_commands = commands.shape[-2]
            d_tau = {}
            for j in driving:
                inside = ((commands[..., j, :] + gravity).abs() < self.effort).to(q.dtype)[
                    ..., None
                ]
                picked = [eye if k == j else none for k in range(n_commands)]
                d_tau[j] = inside * torch.cat([gravity_q, none, *picked], -1)  # [..., n, (3+h)n]
            rest = [none] * n_commands
            d_q, d_qd = torch.cat([eye, none, *rest], -1), torch.cat([none, eye, *rest], -1)
            d_start = self._point_jacobian(frames, start)
        damping = torch.diag(dyn.joint_damping)
        for s in range(self.config.substeps):
            if s > 0:
                frames = dyn.frames(q)
            held = tau[self.late[s]] - dyn.joint_damping * qd
            if jacobian:
                wrench, D = dyn.link_damping_with_jacobian(frames, qd, *LINK_DAMPING)
                qdd, id_q, id_qd, M = dyn.forward_dynamics_derivatives(frames, qd, held, wrench, D)
                rhs = d_tau[self.late[s]] - id_q @ d_q - (id_qd + damping) @ d_qd
                d_qd = d_qd + self.h * torch.linalg.solve(M, rhs)
                d_q = d_q + self.h * d_qd
            else:
                wrench = dyn.link_damping(frames, qd, *LINK_DAMPING)
                qdd = dyn.forward_dynamics_at(frames, qd, held, wrench)
            qd = qd + self.h * qdd
            q = q + self.h * qd
        frames = dyn.frames(q)
        end = dyn.points(frames).flatten(-2)
        if not jacobian:
            return q, qd, end - start, None
        d_moved = self._point_jacobian(frames, end) @ d_q
        d_moved[..., : q.shape[-1]] -= d_start
        return q, qd, end - start, torch.cat([d_q, d_qd, d_moved], -2)

    def _gravity(self, frames: Frames, zeros: Tensor) -> Tensor:
        """The compensated gravity torque before κ: ``(1 - ρ) g_URDF(q) + ρ g(q)`` (the URDF's
        alone, bit for bit, where ρ = 0)."""
        urdf = self.urdf.inverse_dynamics_at(frames, zeros, zeros)
        if not self.own:
            return urdf
        own = self.dynamics.inverse_dynamics_at(frames, zeros, zeros)
        return (1.0 - self.own) * urdf + self.own * own

    def _point_jacobian(self, frames: Frames, points: Tensor) -> Tensor:
        """``dP/dq: [..., 6, n]`` of the points ``P: [..., 6]`` (tip, top) on the last body:
        ``v_k + omega_k x P`` per joint motion ``S_k = (omega_k, v_k)``."""
        S = self.dynamics.motion_subspace(frames)[..., None, :, :]  # [..., 1, n, 6]
        P = points.unflatten(-1, (2, 1, 3))  # [..., 2, 1, 3]
        dP = S[..., 3:] + torch.linalg.cross(S[..., :3], P)  # [..., 2, n, 3]
        return dP.transpose(-1, -2).flatten(-3, -2)


def stabilising_inertia(dynamics: ArmDynamics, config: WorldConfig) -> list[float]:
    """Per actuated joint, the isotropic inertia the world adds to its child link:
    ``max(0, margin b h - m)`` with m = ``1 / (M(0)^{-1})_jj`` the joint's effective inertia,
    b its damping and h the physics step (see ``PegWorld._stabilise_damping``)."""
    q = torch.zeros(dynamics.n, dtype=torch.float64, device=dynamics.device)
    m = 1.0 / torch.diagonal(torch.linalg.inv(dynamics.mass_matrix(q)))
    need = config.damping_margin * dynamics.joint_damping * config.dt / config.substeps
    return torch.where(m < need, need - m, torch.zeros_like(m)).tolist()
