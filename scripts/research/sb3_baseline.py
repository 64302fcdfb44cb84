"""A model-free baseline: stable-baselines3 SAC (or PPO) on one condition of the peg task.

    python scripts/research/sb3_baseline.py --hole 0.02 0.02 --steps 600000 --cpu-minutes 20 \\
        --gps runs/gps-hole-0.02-0.02 --out runs/sb3-sac-hole-0.02-0.02

Trains on ``lolgps_torch/PegInsertionNormalized-v0`` (actions in [-1, 1] times the efforts,
reward -l(x_t, u_t), T steps per episode) with the hole fixed at ``--hole``, for ``--steps``
environment steps, or until training has used ``--cpu-minutes`` of CPU time or
``--wall-minutes`` of wall time, whichever comes first. Every training episode (rollout) is
logged: its return, final tip distance and success (final tip distance < success threshold). After training, one rollout of the
deterministic policy is scored.

``--gps DIR`` reads the trajectory-centric learner's run on the same condition (made by
``scripts/train_condition.py --out DIR``: summary.json and metrics.jsonl) and puts its rollouts
(iterations x ``--gps-samples``) next to the baseline's. Writes OUT/result.json and
OUT/learning_curve.png (final tip distance per rollout, both learners).
Needs stable-baselines3: ``pip install 'lolgps_torch[sb3]'``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, cast

import gymnasium as gym
import matplotlib
import numpy as np

from lolgps_torch.cli import run
from lolgps_torch.data.run_folder import RunFolder, read_json, write_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.gym_env import DEFAULT_URDF, NORMALIZED_ENV_ID, PegInsertionEnv
from lolgps_torch.sim.plant import PlantConfig
from lolgps_torch.task import TaskConfig

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--urdf", default=DEFAULT_URDF, help="the arm's URDF (default: KUKA)")
    parser.add_argument("--hole", type=float, nargs=2, default=(0.02, 0.02), metavar=("DX", "DY"))
    parser.add_argument("--algo", choices=("sac", "ppo"), default="sac")
    parser.add_argument("--steps", type=int, default=600_000, help="environment step budget")
    parser.add_argument(
        "--cpu-minutes", type=float, default=None, help="stop after this much CPU time"
    )
    parser.add_argument(
        "--wall-minutes", type=float, default=None, help="stop after this much wall time"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--limits",
        choices=("reflex", "off"),
        default="reflex",
        help="the arm's controller stops an episode where a joint passes a limit, or lets it "
        "go on (default: reflex)",
    )
    parser.add_argument("--gps", default=None, help="train_condition.py output folder to compare")
    parser.add_argument("--gps-samples", type=int, default=5, help="rollouts per GPS iteration")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--figure", default=None, help="also write the figure here")
    parser.add_argument("--every", type=int, default=50, help="print a line every N episodes")
    return parser.parse_args()


def make_callback(cpu_seconds: float, wall_seconds: float, every: int) -> Any:
    """A stable-baselines3 callback that logs every finished episode (steps so far, return,
    final tip distance, success, CPU s) and stops training once the process CPU time reaches
    ``cpu_seconds`` or ``time.perf_counter()`` reaches ``wall_seconds``."""
    from stable_baselines3.common.callbacks import BaseCallback

    class EpisodeLog(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.episodes: list[dict[str, Any]] = []
            self.returns = 0.0

        def _on_step(self) -> bool:
            self.returns += float(self.locals["rewards"][0])
            if self.locals["dones"][0]:
                info = self.locals["infos"][0]
                record = {
                    "episode": len(self.episodes) + 1,
                    "steps": int(self.num_timesteps),
                    "return": self.returns,
                    "final_distance": float(info["tip_distance"]),
                    "success": bool(info["success"]),
                    "cpu_seconds": time.process_time(),
                }
                self.episodes.append(record)
                self.returns = 0.0
                if record["episode"] % every == 0:
                    recent = self.episodes[-every:]
                    rate = np.mean([e["success"] for e in recent])
                    print(
                        f"episode {record['episode']:6d}  steps {record['steps']:8d}  "
                        f"return {record['return']:10.1f}  distance "
                        f"{record['final_distance']:.3f} m  success (last {every}) {rate:.0%}  "
                        f"cpu {record['cpu_seconds'] / 60:.1f} min",
                        flush=True,
                    )
            return time.process_time() < cpu_seconds and time.perf_counter() < wall_seconds

    return EpisodeLog()


def train(args: argparse.Namespace, env: gym.Env[Any, Any]) -> tuple[Any, list[dict[str, Any]]]:
    """Train the chosen algorithm on ``env``; the model and its episode log."""
    from stable_baselines3 import PPO, SAC

    algo = SAC if args.algo == "sac" else PPO
    model = algo("MlpPolicy", env, seed=args.seed, device="cpu", verbose=0)
    cpu = time.process_time() + 60 * (args.cpu_minutes or math.inf)
    wall = time.perf_counter() + 60 * (args.wall_minutes or math.inf)
    callback = make_callback(cpu, wall, args.every)
    model.learn(total_timesteps=args.steps, callback=callback)
    return model, callback.episodes


def evaluate(model: Any, env: gym.Env[Any, Any]) -> dict[str, Any]:
    """One rollout of the deterministic policy: final tip distance (m) and success."""
    obs, _ = env.reset()
    done, info = False, dict[str, Any]()
    while not done:
        action, _ = model.predict(obs, deterministic=True)
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    return {"final_distance": float(info["tip_distance"]), "success": bool(info["success"])}


def gps_result(folder: Path, samples: int) -> dict[str, Any]:
    """The trajectory-centric learner's run: iterations, rollouts, rollouts up to the end of
    the first iteration with a successful rollout, time spent sampling, fitting and solving
    (s), and its per-iteration final distances."""
    run = RunFolder(folder)
    summary = read_json(run.summary_path)
    metrics = run.read_metrics()
    first = next((m["iteration"] for m in metrics if m["success_rate"] > 0), None)
    return {
        "iterations": int(summary["iterations"]),
        "samples_per_iteration": samples,
        "rollouts": int(summary["iterations"]) * samples,
        "rollouts_to_first_success": None if first is None else (first + 1) * samples,
        "noiseless_final_distance": summary["noiseless_final_distance"],
        "seconds": sum(m["time_sample"] + m["time_fit"] + m["time_cstep"] for m in metrics),
        "mean_distance": [m["mean_distance"] for m in metrics],
        "best_distance": [m["best_distance"] for m in metrics],
        "success_rate": [m["success_rate"] for m in metrics],
    }


def plot(result: dict[str, Any], threshold: float, paths: list[Path]) -> None:
    """Final tip distance per rollout of both learners against rollouts (log x)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    episodes = result["episodes"]
    x = np.array([e["episode"] for e in episodes])
    d = np.array([e["final_distance"] for e in episodes])
    label = result["algo"].upper()
    ax.plot(x, d, ".", ms=2, alpha=0.3, color="tab:blue", label=f"{label} rollout")
    if len(d) >= 20:
        smooth = np.convolve(d, np.ones(20) / 20, mode="valid")
        ax.plot(x[19:], smooth, color="tab:blue", label=f"{label} (mean of 20)")
    gps = result.get("gps")
    if gps is not None:
        k = gps["samples_per_iteration"]
        xs = k * (np.arange(len(gps["mean_distance"])) + 1)
        ax.plot(xs, gps["mean_distance"], "o-", color="tab:red", label=f"GPS mean of {k}")
        ax.plot(xs, gps["best_distance"], "v", color="tab:red", mfc="none", label="GPS best")
    ax.axhline(threshold, color="k", ls="--", lw=1, label="success threshold")
    ax.set(xscale="log", yscale="log", xlabel="rollouts (episodes of T steps)")
    ax.set(ylabel="final tip distance (m)", title=f"hole offset {tuple(result['hole'])} m")
    ax.legend(fontsize=8)
    fig.tight_layout()
    for path in paths:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    plt.close(fig)


def summarise(episodes: list[dict[str, Any]], window: int = 20) -> dict[str, Any]:
    """Rollouts until the first success, and the success rate of the last ``window``."""
    first = next((e["episode"] for e in episodes if e["success"]), None)
    recent = episodes[-window:]
    return {
        "rollouts": len(episodes),
        "rollouts_to_first_success": first,
        f"success_rate_last_{window}": float(np.mean([e["success"] for e in recent]))
        if recent
        else 0.0,
    }


def main() -> None:
    args = parse_args()
    if importlib.util.find_spec("stable_baselines3") is None:
        raise LolgpsError("stable-baselines3 is not installed: pip install 'lolgps_torch[sb3]'")
    out = Path(args.out)
    if args.gps and not Path(args.gps).is_dir():
        raise LolgpsError(f"--gps {args.gps}: no such folder")
    hole = (args.hole[0], args.hole[1])
    config = TaskConfig(urdf=args.urdf, plant=PlantConfig(limits=args.limits))
    env = gym.make(NORMALIZED_ENV_ID, task_config=asdict(config), hole_offset=hole)
    task = cast(PegInsertionEnv, env.unwrapped).task
    task.check_reachable(hole)
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    model, episodes = train(args, env)
    wall, cpu = time.perf_counter() - start_wall, time.process_time() - start_cpu
    steps = episodes[-1]["steps"] if episodes else 0
    gps = gps_result(Path(args.gps), args.gps_samples) if args.gps else None
    result = {
        "algo": args.algo,
        "hole": list(hole),
        "seed": args.seed,
        "step_budget": args.steps,
        "cpu_minutes_budget": args.cpu_minutes,
        "wall_minutes_budget": args.wall_minutes,
        "steps": int(model.num_timesteps),
        "steps_in_finished_episodes": steps,
        "wall_seconds": wall,
        "cpu_seconds": cpu,
        **summarise(episodes),
        "deterministic_policy": evaluate(model, env),
        "gps": gps,
        "episodes": episodes,
    }
    write_json(out / "result.json", result)
    threshold = task.config.world.success_threshold
    figures = [out / "learning_curve.png"] + ([Path(args.figure)] if args.figure else [])
    plot(result, threshold, figures)
    env.close()
    print(json.dumps({k: v for k, v in result.items() if k not in ("episodes", "gps")}))
    print(f"wrote {out / 'result.json'} and {', '.join(str(f) for f in figures)}")


if __name__ == "__main__":
    run(main)
