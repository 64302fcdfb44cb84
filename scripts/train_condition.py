"""Learn one hole position with the trajectory-centric loop (no global policy).

    python scripts/train_condition.py --urdf robots/kuka_peg.urdf --hole 0.0 0.0 --seed 0 --out runs/cond

Each iteration samples N rollouts, fits the dynamics and takes the KL-constrained C-step.
Per iteration it prints and appends to OUT/metrics.jsonl: mean cost, mean and best final
tip distance, success rate, epsilon, eta and the time spent sampling, fitting and solving.
OUT also gets config.json and arm.urdf (written once every flag, the folder and the hole's
reachability are checked) and, at the end, summary.json. As in ``lolgps run``, the arm's
gravity compensation is first checked and, where missing, made with the URDF's model
(``--no-detect-gravity``; config.json's ``detected_gravity_compensation``), and its command
delay estimated and allowed for (``--no-detect-delay``; config.json's ``detected_delay``).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, fields, replace

import torch

from lolgps_torch.cli import (
    ConfigFlags,
    add_delay_argument,
    add_gravity_argument,
    add_task_arguments,
    add_workers_argument,
    check_device,
    run,
    task_config,
    workers,
)
from lolgps_torch.commands.probes import (
    allow_for_delay,
    compensate_gravity,
    detect_delay,
    detect_gravity,
)
from lolgps_torch.data.records import IterationRecord
from lolgps_torch.data.run_folder import RunFolder, arm_urdf, as_stored, task_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import LocalConfig, LocalLearner, iterate
from lolgps_torch.lolgps.probes import noiseless_distance
from lolgps_torch.policy import PolicyConfig
from lolgps_torch.robot.placement import pinned
from lolgps_torch.task import PegTask

LOCAL_FLAGS = ConfigFlags(
    LocalConfig(),
    renames={
        "dynamics-prior": ("dynamics.prior",),
        "step-mult-max": ("cstep.step_mult_max",),
        "step-mult-init": ("cstep.step_mult_init",),
    },
)

# the limits its samples are kept within, as the stream's are (a sample or check past the
# arm's own limit is a fault)
LIMITS = ("guard", "guard_limit", "guard_position")
LIMIT_FLAGS = ConfigFlags(
    PolicyConfig(),
    renames={"no-guard": ("guard",)},
    skip=[f.name for f in fields(PolicyConfig) if f.name not in LIMITS],
)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_task_arguments(parser)
    parser.add_argument(
        "--hole",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("DX", "DY"),
        help="hole offset (m) from the nominal position (default: 0 0)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--iterations", type=int, default=15, help="iteration limit (default 15)")
    LOCAL_FLAGS.add_to(parser.add_argument_group("local learner"))
    LIMIT_FLAGS.add_to(parser.add_argument_group("the arm's limits"))
    parser.add_argument(
        "--stop-at-success",
        action="store_true",
        help="stop once at least 3 of 5 samples (60%%) succeed",
    )
    parser.add_argument("--device", default="cpu")
    add_gravity_argument(parser)
    add_delay_argument(parser)
    add_workers_argument(parser)
    args = parser.parse_args()
    if args.iterations < 1:
        raise LolgpsError(f"--iterations {args.iterations}: must be >= 1")
    return args


def _print(record: IterationRecord) -> None:
    print(
        f"iter {record.iteration:2d}  cost {record.mean_cost:9.2f}  "
        f"dist mean {record.mean_distance:.3f} best {record.best_distance:.3f}  "
        f"success {record.success_rate:.0%}  eps {record.epsilon:.1f} eta {record.eta:.3g}  "
        f"t {record.time_sample:.2f}/{record.time_fit:.2f}/{record.time_cstep:.2f} s",
        flush=True,
    )


def learn(learner: LocalLearner, folder: RunFolder, iterations: int, stop_at_success: bool) -> int:
    """Iterate, logging each iteration; returns the number of iterations taken."""
    for i in range(iterations):
        _, _, record = iterate(learner, learner.p_cur, None, False, (0, i, 0.0))
        folder.append_metrics(record.to_json())
        _print(record)
        if stop_at_success and record.success_rate >= 0.6:
            break
    if not torch.isfinite(learner.p_cur.k).all():
        raise LolgpsError("the controller diverged (non-finite gains)")
    return i + 1


def main() -> None:
    args = parse_args()
    device = check_device(args.device)
    config: LocalConfig = LOCAL_FLAGS.build(args)
    tcfg, offset = task_config(args), (float(args.hole[0]), float(args.hole[1]))
    tcfg = replace(tcfg, placement=replace(tcfg.placement, positions=(offset,)))
    folder, urdf_text = RunFolder(args.out), arm_urdf(tcfg)
    if folder.has_config():
        raise LolgpsError(f"{folder.path} already holds a run; choose another --out")
    folder.check_writable()
    uncompensated = detect_gravity(tcfg, args.detect_gravity)
    if uncompensated:
        tcfg = compensate_gravity(tcfg)
    delay = detect_delay(tcfg, args.detect_delay)
    if delay > 0.0:
        tcfg, config = allow_for_delay(tcfg, config, delay)
    torch.manual_seed(args.seed)
    task = PegTask(tcfg, config.samples, device=str(device), workers=workers(args))
    try:  # the placement has checked that the hole is reachable
        settings = {"hole": list(offset), "seed": args.seed, "iterations": args.iterations}
        settings |= {"detected_gravity_compensation": "none"} if uncompensated else {}
        settings |= {"detected_delay": delay} if delay > 0.0 else {}
        placed = replace(tcfg, placement=pinned(tcfg.placement, task.geometry))
        record = {**settings, "task": task_json(placed, urdf_text), "local": asdict(config)}
        folder.start(as_stored(record), urdf_text)
        limits = LIMIT_FLAGS.build(args).limits()
        learner = LocalLearner(task, offset, config, seed=args.seed, limits=limits)
        taken = learn(learner, folder, args.iterations, args.stop_at_success)
        distance = noiseless_distance(task, learner.p_cur, offset, limits)
    finally:
        task.close()
    folder.write_summary(
        {
            "hole": list(offset),
            "seed": args.seed,
            "iterations": taken,
            "noiseless_final_distance": distance,
        }
    )
    print(f"noiseless final distance of the last controller: {distance:.4f} m")


if __name__ == "__main__":
    run(main)
