"""What a stream run prints: a line per record and per finished condition, and the table it
ends with."""

from __future__ import annotations

from lolgps_torch.data.records import (
    ConditionSummary,
    DistillRecord,
    IdentifiedRecord,
    IterationRecord,
)
from lolgps_torch.data.run_folder import RunFolder


def record_line(record: IterationRecord | IdentifiedRecord | DistillRecord, total: int) -> str:
    """A record's line: an iteration's, an S-step's or the arm identified, at condition m of
    ``total``."""
    if isinstance(record, DistillRecord):
        return f"S-step took {record.time_distill:.1f}s"
    if isinstance(record, IdentifiedRecord):
        return (
            f"condition {record.condition + 1}/{total}  arm identified: payload "
            f"{record.payload:.3f} kg, gravity compensation x {record.compensation:.3f} "
            f"(its own gravity's share {record.own_compensation:.2f}); one-step "
            f"joint-speed error on its first rollouts {record.error_identified:.4f} rad/s "
            f"(URDF model {record.error_urdf:.4f}, the simulated arm's own "
            f"{record.error_plant:.4f}; {record.transitions} free transitions)"
        )
    return (
        f"condition {record.condition + 1}/{total}  iter {record.iteration:2d}  "
        f"cost {record.mean_cost:8.2f}  distance mean {record.mean_distance:.3f} "
        f"best {record.best_distance:.3f}  success {record.success_rate:4.0%}  "
        f"faults {record.faults}  "
        f"[{record.time_sample:.2f}s sample, {record.time_fit:.2f}s fit, "
        f"{record.time_cstep:.2f}s C-step]"
    )


def condition_line(entry: ConditionSummary, total: int) -> str:
    """A finished condition's line: its first success, distances, faults and rollouts."""
    failure = f"; failed: {entry.failure}" if entry.failure else ""
    kinds = ", ".join(f"{n} {kind}s" for kind, n in entry.arm_rollouts.items())
    stopped = sum(entry.arm_faults.values())
    seconds = "" if entry.arm_seconds is None else f", {entry.arm_seconds:.0f} s on the arm"
    if entry.model_rollouts:
        seconds += (
            f"; {entry.model_rollouts} rollouts on the arm's model ({entry.model_faults} "
            "stopped at a limit)"
        )
    return (
        f"condition {entry.condition + 1}/{total} done: first success at iteration "
        f"{entry.first_success_iteration}, p_cur distance {entry.local_final_distance:.4f}, "
        f"global policy distance {entry.policy_final_distance_after:.4f}, faults "
        f"{entry.faults}; arm rollouts {sum(entry.arm_rollouts.values())} ({kinds}; "
        f"{stopped} stopped at a limit){seconds}{failure}"
    )


def print_table(summary: list[ConditionSummary], folder: RunFolder) -> None:
    """The table a stream ends with: one row per condition, and the positions the policy
    alone reaches."""
    print(
        f"\n{'cond':>4} {'offset (m)':>17} {'iters':>5} {'1st ok':>6} {'p_cur':>8} "
        f"{'pi after':>9} {'pi end':>8}"
    )
    for e in summary:
        first = "-" if e.first_success_iteration is None else str(e.first_success_iteration)
        print(
            f"{e.condition:>4} ({e.offset[0]:+.3f}, {e.offset[1]:+.3f}) {e.iterations:>5} "
            f"{first:>6} {e.local_final_distance:8.4f} {e.policy_final_distance_after:9.4f} "
            f"{e.policy_final_distance_end:8.4f}"
        )
    solved = sum(bool(e.policy_success_end) for e in summary)
    print(
        f"global policy alone succeeds at {solved}/{len(summary)} training positions; "
        f"results in {folder.path}"
    )
