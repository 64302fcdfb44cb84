"""Learn single conditions over holes x seeds (x arms) with scripts/train_condition.py and
print the markdown table of first successful iteration and final noiseless distance.

    python scripts/research/condition_table.py --urdf robots/kuka_peg.urdf --seeds 0 1 2 3 4 \\
        --holes 0 0 0.03 0.03 -0.03 0.03 0.03 -0.03 -0.03 -0.03 --iterations 10 --out runs/table

An iteration succeeds when at least --min-success (default 3) of its 5 samples end with the tip
within 0.06 m of the target. Each run's metrics.jsonl and summary.json stay under --out.
--dynamics-prior, --step-mult-init and --step-mult-max are passed on to every run (the C-step's
multiplier of ``epsilon = kl_step * step_mult * T``, docs/ALGORITHM.md section 5).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path
from typing import get_args

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder, read_json
from lolgps_torch.dynamics.fit import PriorSource
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.trajopt.config import CStepConfig

TRAIN_CONDITION = Path(__file__).resolve().parents[1] / "train_condition.py"


def learn(
    urdf: str, hole: tuple[float, float], seed: int, iterations: int, out: str, local: list[str]
) -> RunFolder:
    """One run of scripts/train_condition.py into ``out`` with the local learner's flags
    ``local``."""
    cmd = [sys.executable, str(TRAIN_CONDITION), "--urdf", urdf, "--hole", str(hole[0])]
    cmd += [str(hole[1]), "--seed", str(seed), "--iterations", str(iterations), "--out", out]
    cmd += local
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise LolgpsError(f"{' '.join(cmd)} failed: {proc.stderr.strip().splitlines()[-1]}")
    return RunFolder(out)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--urdf", nargs="+", default=["robots/kuka_peg.urdf"], help="one or more arms"
    )
    parser.add_argument(
        "--holes", type=float, nargs="+", default=[0.0, 0.0], help="dx dy pairs (m)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--min-success", type=int, default=3)
    parser.add_argument(
        "--dynamics-prior",
        choices=get_args(PriorSource),
        default=LocalConfig().dynamics.prior,
        help="passed on (default %(default)s)",
    )
    steps = CStepConfig()
    parser.add_argument(
        "--step-mult-init", type=float, default=steps.step_mult_init, help="passed on"
    )
    parser.add_argument(
        "--step-mult-max", type=float, default=steps.step_mult_max, help="passed on"
    )
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    local = ["--dynamics-prior", args.dynamics_prior]
    local += ["--step-mult-init", str(args.step_mult_init)]
    local += ["--step-mult-max", str(args.step_mult_max)]
    if len(args.holes) % 2:
        raise LolgpsError("--holes needs dx dy pairs")
    holes = list(zip(args.holes[::2], args.holes[1::2], strict=True))
    print("| arm | hole (m) | seed | first success (iteration) | noiseless final distance (m) |")
    print("|---|---|---|---|---|")
    for urdf in args.urdf:
        arm = os.path.splitext(os.path.basename(urdf))[0]
        for dx, dy in holes:
            for seed in args.seeds:
                out = os.path.join(args.out, f"{arm}_{dx:+.3f}_{dy:+.3f}_s{seed}")
                folder = learn(urdf, (dx, dy), seed, args.iterations, out, local)
                rates = [r["success_rate"] for r in folder.read_metrics()]
                first = next(
                    (i for i, r in enumerate(rates) if r * 5 >= args.min_success - 1e-9), None
                )
                final = read_json(folder.summary_path)["noiseless_final_distance"]
                print(
                    f"| {arm} | ({dx:+.3f}, {dy:+.3f}) | {seed} | "
                    f"{'-' if first is None else first} | {final:.4f} |",
                    flush=True,
                )


if __name__ == "__main__":
    run(main)
