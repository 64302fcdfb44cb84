"""Where the peg comes down to the hole's mouth: how far to the side, and at which step.

    python scripts/research/mouth.py RUN [RUN ...] [--above 5]

A peg that reaches the mouth's height more than the mouth's clearance (4 mm a side by default)
beside the hole's axis lands on the plate, and a policy rarely lifts it off again. Per
condition m of each run, for its teachers (the mean of D_g(m)'s samples) and for the final
global policy's noiseless rollout at the condition's hole:

- ``step``: the first control step at which the tip is within ``--above`` mm above the
  mouth, ``z_t <= depth + above`` (z of ``p_tip - p*_tip``, whose target is the hole's floor);
- ``lateral``: the tip's distance from the hole's axis there, ``|(p_tip - p*_tip)_xy|`` (mm);
- ``final``: the policy's final distance to the target (m).

Then per run: the steps' range and the largest lateral error of the teachers and of the
policy, and how many of the policy's arrivals lie beyond the clearance. The descent schedule
(the cost's ``descent_steps``) sets when the teachers reach the mouth; an arm kept within its
velocity limits needs steps to come over the hole from its start, and reaches the mouth still
beside it when the schedule brings it down before that approach ends.
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.lolgps.run import LoadedRun, load_run
from lolgps_torch.policy import policy_actor

Arrival = tuple[int | None, float]  # (step, lateral mm)


def arrivals(tip: torch.Tensor, depth: float, above: float) -> list[Arrival]:
    """``(step, lateral mm)`` per trajectory of tip errors ``tip: [N, T, 3]`` (m): the first
    step with ``z <= depth + above`` and the lateral error there (None, nan: never)."""
    rows: list[Arrival] = []
    for one in tip:
        down = (one[:, 2] <= depth + above).nonzero()
        if len(down) == 0:
            rows.append((None, float("nan")))
            continue
        t = int(down[0])
        rows.append((t, 1000.0 * float(one[t, :2].norm())))
    return rows


def measure(
    loaded: LoadedRun, above: float
) -> tuple[list[Arrival], list[Arrival], list[float], float]:
    """The teachers' and the final policy's arrivals per condition, the policy's final
    distances (m) and the mouth's clearance (m)."""
    task = loaded.make_task()
    try:
        tip = task.layout.points.start
        world = loaded.info.task.world
        teachers = torch.stack([r.samples.x.mean(0)[:, tip : tip + 3] for r in loaded.records])
        policy = loaded.policy(loaded.records[-1].condition)
        offsets = [r.offset for r in loaded.records]
        rollouts = task.sample(policy_actor(policy, task.model), offsets)
        return (
            arrivals(teachers, world.depth, above),
            arrivals(rollouts.x[..., tip : tip + 3], world.depth, above),
            rollouts.final_distance.tolist(),
            world.clearance_mouth,
        )
    finally:
        task.close()


def _span(rows: list[Arrival]) -> str:
    steps = [t for t, _ in rows if t is not None]
    lateral = max((side for t, side in rows if t is not None), default=float("nan"))
    span = f"{min(steps)}-{max(steps)}" if steps else "never"
    return f"steps {span}, lateral at most {lateral:.1f} mm"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders")
    parser.add_argument(
        "--above", type=float, default=5.0, help="mm above the mouth that counts as at it"
    )
    args = parser.parse_args()
    loaded = [load_run(path) for path in args.runs]
    for path, one in zip(args.runs, loaded, strict=True):
        teachers, policy, finals, clearance = measure(one, args.above / 1000.0)
        print(f"{path}: at the mouth (step, lateral mm): teachers; policy, its final distance")
        for record, (t, side), (tp, sp), final in zip(
            one.records, teachers, policy, finals, strict=True
        ):
            print(
                f"  condition {record.condition} ({record.offset[0]:+.3f}, "
                f"{record.offset[1]:+.3f}): teachers {t}, {side:.1f}; policy {tp}, {sp:.1f}, "
                f"{final:.3f} m"
            )
        wide = sum(1 for t, side in policy if t is None or side > 1000.0 * clearance)
        print(
            f"  teachers {_span(teachers)}; policy {_span(policy)}; "
            f"{wide} of {len(policy)} policy arrivals beyond the {1000.0 * clearance:.0f} mm "
            f"clearance or never; {sum(f < one.info.task.world.success_threshold for f in finals)}"
            f" of {len(finals)} reached"
        )


if __name__ == "__main__":
    run(main)
