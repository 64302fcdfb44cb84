"""Where a stream's time goes on each simulator: the same stream profiled (cProfile) on
PyBullet and on MuJoCo, one after the other, with one rollout worker, and its parts side by
side.

    python scripts/research/stream_profile.py --out DIR [--urdf robots/kuka_peg.urdf]
        [--seed 0] [--sims pybullet mujoco] [-- RUN_STREAM_FLAGS ...]
    python scripts/research/stream_profile.py --out DIR --summarise

Each simulator's stream runs as ``scripts/run_stream.py --urdf URDF --sim <sim> --workers 1
--seed S --out DIR/<sim>`` under cProfile timed by the process's CPU time (other processes on
a shared machine disturb it less than the wall clock), the profile in ``DIR/<sim>.prof``;
``--summarise`` reads the profiles already in DIR (of the code as it is now: functions are
found by their lines). Printed per simulator: the cumulative seconds of the stream, its
sampling (rollouts counted by resets, control steps by the commands issued) and, inside it,
the physics steps, the gravity compensation, the state and the actors (the policy's, the
linear-Gaussian controllers'); the S-steps (their Adam loops and the rest: the policy's
rollouts); local learning (the plan on the model, the dynamics fits, the C-steps); and the
sampling per rollout, with the MuJoCo / PyBullet ratio of each. The profiler's own cost
inflates the many small calls of sampling, so compare the two simulators' columns, not the
seconds with those of an unprofiled run.
"""

from __future__ import annotations

import argparse
import ast
import pstats
import subprocess
import sys
from pathlib import Path

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError

STREAM = Path(__file__).resolve().parents[2] / "scripts" / "run_stream.py"
# a script run under cProfile timed by this process's CPU time, which other processes on a
# shared machine disturb less than the wall clock: argv = [profile, script, flags...]
PROFILED = """
import cProfile, runpy, sys, time
profile, script = sys.argv[1:3]
sys.argv = sys.argv[2:]
profiler = cProfile.Profile(time.process_time)
profiler.enable()
try:
    runpy.run_path(script, run_name="__main__")
finally:
    profiler.disable()
    profiler.dump_stats(profile)
"""
SIMS = ("pybullet", "mujoco")
# (row, the qualified names whose cumulative seconds it sums); nested rows are indented
PARTS: list[tuple[str, tuple[str, ...]]] = [
    ("stream", ("StreamLearner.run",)),
    ("sampling", ("PegTask.sample",)),
    ("  physics steps", ("PegWorld._physics_step", "_physics_steps")),
    ("  gravity compensation", ("PegWorld.gravity_compensation", "MujocoWorld.gravity_compensation")),
    ("  state (observe)", ("World.observe",)),
    ("  policy actor", ("PolicyActor.__call__",)),
    ("  within the limits", ("within_limits", "LimitedActor._inertia")),
    ("  linear-Gaussian actor", ("LinearGaussianActor.__call__", "RowwiseLinearGaussian.__call__")),
    ("S-steps", ("CheckedSStep.__call__",)),
    ("  Adam loops (distill)", ("distill",)),
    ("local learning", ("StreamLearner.learn_locally",)),
    ("  plan on the model", ("plan_on_model",)),
    ("  dynamics fits", ("LocalLearner.fit",)),
    ("  C-steps", ("c_step",)),
]  # fmt: skip
COUNTS = {"rollouts": "World.reset", "control steps": "World._command"}


def qualified_names(path: str) -> dict[int, str]:
    """Each function's qualified name in the source file ``path``, by the line its code
    starts on (the ``def``, or its first decorator)."""
    names: dict[int, str] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                names[child.lineno] = name
                for decorator in child.decorator_list[:1]:
                    names[decorator.lineno] = name
                visit(child, f"{name}.<locals>.")

    visit(ast.parse(Path(path).read_text()), "")
    return names


def summarise(profile: Path) -> dict[str, float]:
    """The seconds of each of :data:`PARTS` and the calls of each of :data:`COUNTS` in a
    cProfile file (functions of this package only)."""
    stats = pstats.Stats(str(profile)).stats  # type: ignore[attr-defined]
    files: dict[str, dict[int, str]] = {}
    cumulative: dict[str, float] = {}
    calls: dict[str, int] = {}
    for (path, line, _), (_, ncalls, _, cum, _) in stats.items():
        if "lolgps_torch" not in path or not Path(path).exists():
            continue
        if path not in files:
            files[path] = qualified_names(path)
        name = files[path].get(line)
        if name is not None:
            cumulative[name] = cumulative.get(name, 0.0) + cum
            calls[name] = calls.get(name, 0) + ncalls
    out = {row: sum(cumulative.get(n, 0.0) for n in names) for row, names in PARTS}
    out |= {row: float(calls.get(name, 0)) for row, name in COUNTS.items()}
    out["sampling per rollout (ms)"] = 1e3 * out["sampling"] / max(out["rollouts"], 1.0)
    return out


def profile_stream(sim: str, args: argparse.Namespace, extra: list[str]) -> Path:
    """Run the stream on ``sim`` under cProfile; the profile's path."""
    out = Path(args.out)
    profile = out / f"{sim}.prof"
    flags = ["--urdf", args.urdf, "--sim", sim, "--workers", "1", "--seed", str(args.seed),
             "--out", str(out / sim), *extra]  # fmt: skip
    command = [sys.executable, "-c", PROFILED, str(profile), str(STREAM), *flags]
    print(f"python scripts/run_stream.py {' '.join(flags)}  (profiled: {profile})", flush=True)
    with open(out / f"{sim}.log", "w") as log:
        if subprocess.run(command, stdout=log, stderr=subprocess.STDOUT).returncode != 0:
            raise LolgpsError(f"the stream on {sim} failed: see {out / f'{sim}.log'}")
    return profile


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", required=True, help="folder of the runs and their profiles")
    parser.add_argument("--urdf", default="robots/kuka_peg.urdf", help="the arm's URDF")
    parser.add_argument("--seed", type=int, default=0, help="the stream's seed (default 0)")
    parser.add_argument("--sims", nargs="+", choices=SIMS, default=list(SIMS))
    parser.add_argument("--summarise", action="store_true", help="only read DIR's profiles")
    args, extra = parser.parse_known_args()
    extra = [a for a in extra if a != "--"]
    out = Path(args.out)
    if args.summarise:
        profiles = {sim: out / f"{sim}.prof" for sim in args.sims}
        missing = [str(p) for p in profiles.values() if not p.exists()]
        if missing:
            raise LolgpsError(f"no profile {', '.join(missing)}")
    else:
        out.mkdir(parents=True, exist_ok=True)
        profiles = {sim: profile_stream(sim, args, extra) for sim in args.sims}
    table = {sim: summarise(path) for sim, path in profiles.items()}
    sims = list(table)
    ratio = len(sims) == 2
    print(f"{'':28}" + "".join(f"{sim:>12}" for sim in sims) + ("   ratio" if ratio else ""))
    for row in table[sims[0]]:
        values = [table[sim][row] for sim in sims]
        line = f"{row:28}" + "".join(f"{v:12.3f}" for v in values)
        if ratio and values[0] > 0:
            line += f"  {values[1] / values[0]:6.2f}"
        print(line)


if __name__ == "__main__":
    run(main)
