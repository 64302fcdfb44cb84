"""How tidy a run's teachers are, and how far apart neighbouring ones hold the arm.

    python scripts/research/teachers.py RUN [RUN ...] [--steps 10 20 40 99]

The global policy interpolates between its teachers, the local controllers whose successful
samples make up each condition's D_g. Per condition m of each run, from the mean of D_g(m)'s
samples:

- ``lateral``: the largest lateral error of the peg's tip, ``max_t |(p_tip - p*_tip)_xy|`` (mm),
  from step 10 to the end of the descent schedule (the cost's ``descent_steps``), while the
  lifted targets ask the peg to come down straight over the mouth. A teacher that reaches the
  mouth 10-30 mm to the side and slides in succeeds; a policy fitted to such teachers lands on
  the plate beside the mouth where they disagree.
- ``free``: with ``q_m(t)`` the mean joint angles at step t and n the nearest other condition
  by hole offset, the part of their difference in posture that moves neither of the points
  the cost fixes (the self-motion of an arm with more joints than those 6 coordinates),

      free_t(m) = | (I - J^+ J) (q_n(t) - q_m(t)) |      J = d[p_tip; p_top]/dq at q_m(t)

  (rad, J^+ the pseudo-inverse), at ``--steps``.

- ``aligned``: the first step at which the mean tip is within ``--within`` (mm, default 5)
  of the hole's axis, ``|(p_tip - p*_tip)_xy|``: where the approach from the start pose ends
  and the straight descent over the mouth begins.

Then per run: the mean of the conditions' ``lateral``, the largest ``free`` and the range of
``aligned``.
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.run import LoadedRun, load_run


def lateral_errors(loaded: LoadedRun, first: int = 10) -> list[float]:
    """Each condition's largest lateral tip error (mm) of its D_g mean from step ``first`` to
    the end of the descent schedule."""
    layout = loaded.info.task.world.layout(loaded.records[0].samples.u.shape[-1])
    last = max(first + 1, loaded.info.task.cost.descent_steps + 1)
    tip = [r.samples.x.mean(0)[first:last, layout.points][:, :2] for r in loaded.records]
    return [1000.0 * float(xy.norm(dim=-1).max()) for xy in tip]


def aligned_steps(loaded: LoadedRun, within: float) -> list[int | None]:
    """Each condition's first step at which its D_g mean tip is within ``within`` (mm) of the
    hole's axis (None: never)."""
    layout = loaded.info.task.world.layout(loaded.records[0].samples.u.shape[-1])
    steps: list[int | None] = []
    for record in loaded.records:
        xy = record.samples.x.mean(0)[:, layout.points][:, :2]
        near = (1000.0 * xy.norm(dim=-1) <= within).nonzero()
        steps.append(int(near[0]) if len(near) else None)
    return steps


def free_differences(loaded: LoadedRun, steps: list[int]) -> list[tuple[int, list[float]]]:
    """``(n, [free_t(m) for t in steps])`` for every condition m (n: its nearest)."""
    task = loaded.make_task(n_worlds=1)
    try:
        layout = task.layout
        offsets = torch.tensor([r.offset for r in loaded.records], dtype=torch.float64)
        means = torch.stack([r.samples.x.mean(0)[:, layout.q] for r in loaded.records])
        rows = []
        for m in range(len(loaded.records)):
            gaps = (offsets - offsets[m]).norm(dim=-1)
            gaps[m] = torch.inf
            n = int(gaps.argmin())
            q = means[m, steps]  # [S, n_joints]
            J = task.kinematics.jacobian(q)  # [S, 6, n_joints]
            free = torch.eye(q.shape[-1], dtype=q.dtype) - torch.linalg.pinv(J) @ J
            d = (free @ (means[n, steps] - q)[..., None])[..., 0]
            rows.append((n, d.norm(dim=-1).tolist()))
        return rows
    finally:
        task.close()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders")
    parser.add_argument("--steps", type=int, nargs="+", default=[10, 20, 40, 99])
    parser.add_argument("--within", type=float, default=5.0, help="mm, for aligned")
    args = parser.parse_args()
    loaded = [load_run(path) for path in args.runs]
    for path, one in zip(args.runs, loaded, strict=True):
        T = one.records[0].samples.x.shape[1]
        if not all(0 <= t < T for t in args.steps):
            raise LolgpsError(f"--steps must lie in [0, {T}), got {args.steps}")
        if len(one.records) < 2:
            raise LolgpsError(f"{path}: one condition, no neighbour to compare with")
    for path, one in zip(args.runs, loaded, strict=True):
        lateral, free = lateral_errors(one), free_differences(one, args.steps)
        aligned = aligned_steps(one, args.within)
        print(f"{path}: lateral (mm); free posture difference to the nearest (rad) at steps "
              f"{args.steps}; aligned (step)")  # fmt: skip
        rows = zip(one.records, lateral, free, aligned, strict=True)
        for record, side, (n, gaps), step in rows:
            print(
                f"  condition {record.condition} ({record.iterations} iterations, nearest {n}): "
                f"lateral {side:.1f}; free "
                + " ".join(f"{v:.3f}" for v in gaps)
                + f"; aligned {step}"
            )
        reached = [step for step in aligned if step is not None]
        span = f"{min(reached)}-{max(reached)}" if reached else "never"
        print(
            f"  mean lateral {sum(lateral) / len(lateral):.1f} mm, "
            f"largest free {max(max(gaps) for _, gaps in free):.3f} rad, aligned at steps {span}"
        )


if __name__ == "__main__":
    run(main)
