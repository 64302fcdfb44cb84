"""How much of the joint speeds a brake fitted to D_g takes away, by the arm's own model.

    python scripts/research/brake_gain.py SWEEP_OR_RUN ... [--poses N]

A brake fitted to the data acts ``u = A qd`` with ``A = -beta B^-1``, B the speed change per
unit torque over one control step fitted to D_g's transitions by least squares,
``q-dot_{t+1} - q-dot_t ~ B u_t + c`` (the guard's brake before it took the arm's model,
``-beta M(q) / dt``, :mod:`lolgps_torch.policy.guard`). On the arm's rigid-body model a torque
held over a control step ``dt`` changes the speeds by about ``dt M(q)^-1 u``, so the brake's
step maps the speeds by

    qd' = (1 + dt M(q)^-1 A) qd = G(q) qd.

With ``A = -beta M / dt`` the map is ``(1 - beta) 1``; a brake is stable at q when the
spectral radius of G(q) is below 1, and it removes energy only where the symmetric part of A
is negative definite. For each evaluated run (a sweep folder stands for every one in it) this
prints, for the brake fitted to the whole replay with the run's beta: the spectral radius of G at the mean pose of D_g and at
``--poses`` poses drawn uniformly within the joint limits (the largest and the share above 1),
and the largest eigenvalue of A's symmetric part (positive: the brake can push energy in).
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import evaluated_runs
from lolgps_torch.lolgps.run import load_run


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folders", nargs="+", help="evaluated run folders or sweep folders")
    parser.add_argument("--poses", type=int, default=200, help="poses within the limits")
    return parser.parse_args()


def fitted_brake(x: torch.Tensor, u: torch.Tensor, qd: slice, beta: float) -> torch.Tensor:
    """``-beta B^-1`` for rollouts ``x: [M, T+1, dX]`` (joint speeds at ``qd``), ``u: [M, T, dU]``."""
    speeds = x[..., qd]
    change = (speeds[:, 1:] - speeds[:, :-1]).flatten(0, 1)
    actions = u.flatten(0, 1)
    design = torch.cat([actions, torch.ones_like(actions[:, :1])], dim=1)
    solution = torch.linalg.solve(design.T @ design, design.T @ change)
    return -beta * torch.linalg.inv(solution[:-1].T)


def spectral_radius(A: torch.Tensor, M: torch.Tensor, dt: float) -> torch.Tensor:
    """``rho(1 + dt M^-1 A)`` for mass matrices ``M: [P, n, n]`` -> ``[P]``."""
    G = torch.eye(A.shape[0], dtype=A.dtype) + dt * torch.linalg.solve(M, A.expand_as(M))
    return torch.linalg.eigvals(G).abs().amax(-1)


def main() -> None:
    args = parse_args()
    print(
        "| run | rho(G) at D_g's mean pose | largest rho(G) within the limits | "
        "share above 1 | largest eigenvalue of sym(A) |"
    )
    print("|---|---|---|---|---|")
    generator = torch.Generator().manual_seed(0)
    for folder in [found for f in args.folders for found in evaluated_runs(f)]:
        loaded = load_run(folder)
        task = loaded.make_task()
        try:
            layout, dynamics = task.layout, task.model.urdf
            full = [r.samples for r in loaded.records if r.samples.final_state is not None]
            x = torch.cat([torch.cat([d.x, d.final_state[:, None]], 1) for d in full])  # type: ignore[index]
            u = torch.cat([d.u for d in full])
            A = fitted_brake(x, u, layout.qd, loaded.info.stream.policy.guard_brake)
            dt = task.config.world.dt
            q_mean = torch.cat([r.samples.x[..., layout.q].flatten(0, 1) for r in loaded.records])
            q_mean = q_mean.mean(0, keepdim=True)
            lower = torch.tensor(task.arm.lower, dtype=torch.float64)
            upper = torch.tensor(task.arm.upper, dtype=torch.float64)
            span = (upper - lower).clamp(max=2 * torch.pi)
            low = torch.where(torch.isfinite(lower), lower, -torch.pi)
            poses = low + span * torch.rand(
                args.poses, A.shape[0], generator=generator, dtype=torch.float64
            )
            at_mean = spectral_radius(A, dynamics.mass_matrix(q_mean), dt)
            within = spectral_radius(A, dynamics.mass_matrix(poses), dt)
            symmetric = torch.linalg.eigvalsh(0.5 * (A + A.T)).amax()
            print(
                f"| {folder.name} | {float(at_mean[0]):.2f} | {float(within.amax()):.2f} | "
                f"{float((within > 1).double().mean()):.2f} | {float(symmetric):.3g} |"
            )
        finally:
            task.close()


if __name__ == "__main__":
    run(main)
