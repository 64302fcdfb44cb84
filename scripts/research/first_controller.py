"""A finished run's first controller at some of its conditions (planned on the arm's model, as
the stream's first iteration there samples it), rolled out in each simulator with fresh
exploration noise: how often the joints get fast, the simulation blows up, or the peg misses.

    python scripts/research/first_controller.py --run RUN [--conditions 4 5] [--batches 20]
        [--sims pybullet mujoco]

Per simulator and condition, ``batches`` batches of the run's samples per iteration, batch b
drawing its noise from seed 1000 + b: the batches that blew up (a :class:`NumericalError`),
the rollouts whose fastest joint passed 20 rad/s, the fastest joint of all (rad/s) and the
success rate of the batches that did not blow up.  ``--contact-refine K`` and
``--contact-time-constant S`` try other contact settings of the MuJoCo world (its
``CONTACT_REFINE`` and ``CONTACT_TIME_CONSTANT``).
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import get_args

import torch

from lolgps_torch.cli import run, run_parser
from lolgps_torch.errors import LolgpsError, NumericalError
from lolgps_torch.lolgps.local import LocalLearner
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.sim.simulator import Simulator
from lolgps_torch.task import PegTask

FAST = 20.0  # rad/s: a joint speed the first controllers' successful rollouts stay well below


def main() -> None:
    parser = run_parser(__doc__, [4, 5])
    parser.add_argument("--batches", type=int, default=20, help="batches per condition")
    parser.add_argument("--sims", nargs="+", choices=get_args(Simulator), default=["pybullet", "mujoco"])  # fmt: skip
    parser.add_argument("--contact-refine", type=int, help="MuJoCo: finer steps in contact")
    parser.add_argument("--contact-time-constant", type=float, help="MuJoCo: in physics steps")
    args = parser.parse_args()
    if args.contact_refine is not None or args.contact_time_constant is not None:
        import lolgps_torch.sim.mujoco_world as mujoco_world

        if args.contact_refine is not None:
            mujoco_world.CONTACT_REFINE = args.contact_refine
        if args.contact_time_constant is not None:
            mujoco_world.CONTACT_TIME_CONSTANT = args.contact_time_constant
    if args.batches < 1:
        raise LolgpsError("--batches must be at least 1")
    loaded = load_run(args.run)
    info = loaded.info
    info.check_conditions(args.conditions)
    warnings.simplefilter("ignore", UserWarning)  # the planning's KL warnings, as in the stream
    for sim in args.sims:
        task = PegTask(replace(info.task, sim=sim), n_worlds=1)
        try:
            for c in args.conditions:
                learner = LocalLearner(task, info.conditions[c], info.stream.local, seed=0)
                blown, speeds, successes = 0, [], []
                for b in range(args.batches):
                    learner.generator.manual_seed(1000 + b)
                    try:
                        samples = learner.sample(learner.p_cur)
                    except NumericalError:
                        blown += 1
                        continue
                    x = torch.cat([samples.x, samples.final_state[:, None]], 1)
                    speeds.append(x[..., task.layout.qd].abs().amax((1, 2)))
                    successes.append(samples.success)
                fast = torch.cat(speeds) if speeds else torch.zeros(0)
                rate = float(torch.cat(successes).double().mean()) if successes else float("nan")
                top = float(fast.max()) if len(fast) else float("nan")
                print(f"{sim:>8} condition {c}: {blown}/{args.batches} batches blew up, "
                      f"{int((fast > FAST).sum())}/{len(fast)} rollouts above {FAST:g} rad/s, "
                      f"fastest {top:.1f} rad/s, success {rate:.3f}", flush=True)  # fmt: skip
        finally:
            task.close()


if __name__ == "__main__":
    run(main)
