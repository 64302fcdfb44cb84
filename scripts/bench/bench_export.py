"""Throughput of the dataset exports on a synthetic run of realistic size.

    python scripts/bench/bench_export.py      # 8 conditions x 45 trajectories x T=100, 7 joints

Builds a run folder (config.json for robots/kuka_peg.urdf, dX = 26, dU = 7, and a replay of
random float64 data, which compresses worse than real trajectories) in a temporary folder,
exports it as HDF5 and as Minari and loads the HDF5 back. MB/s is the uncompressed size of the
exported arrays per second of wall time; the output size on disk is printed alongside.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

from lolgps_torch.cli import run
from lolgps_torch.data import (
    ExportReport,
    ReplayBuffer,
    export_hdf5,
    export_minari,
    load_dataset,
)
from lolgps_torch.data.run_folder import RunFolder, portable_urdf, task_json
from lolgps_torch.robot.arm import load_arm
from lolgps_torch.state import StateLayout
from lolgps_torch.task import TaskConfig
from lolgps_torch.types import ConditionSamples

URDF = str(Path(__file__).resolve().parents[2] / "robots" / "kuka_peg.urdf")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--conditions", type=int, default=8)
    parser.add_argument("--trajectories", type=int, default=45, help="per condition")
    parser.add_argument("--T", type=int, default=100, help="steps per trajectory")
    return parser.parse_args()


def random_samples(M: int, T: int, dX: int, dU: int, g: torch.Generator) -> ConditionSamples:
    f64 = torch.float64
    A = torch.randn(M, T, dU, dU, dtype=f64, generator=g)
    prec = A @ A.mT + torch.eye(dU, dtype=f64)
    return ConditionSamples(
        x=torch.randn(M, T, dX, dtype=f64, generator=g),
        u=torch.randn(M, T, dU, dtype=f64, generator=g),
        cost=torch.rand(M, T, dtype=f64, generator=g),
        final_distance=0.05 * torch.rand(M, dtype=f64, generator=g),
        mean_cur=torch.randn(M, T, dU, dtype=f64, generator=g),
        prec_cur=prec,
        mean_pre=torch.randn(M, T, dU, dtype=f64, generator=g),
        prec_pre=prec.mT.contiguous(),
        has_pre=torch.ones(M, dtype=torch.bool),
    )


def make_run(folder: Path, layout: StateLayout, conditions: int, trajectories: int, T: int) -> int:
    """Write a synthetic run folder; returns the uncompressed size (bytes) of its arrays."""
    task = TaskConfig(urdf=URDF)
    task = replace(task, world=replace(task.world, T=T))
    offsets = [(0.01 * i, -0.01 * i) for i in range(conditions)]
    urdf_text = portable_urdf(URDF)
    config = {
        "method": "lolgps",
        "seed": 0,
        "task": task_json(task, urdf_text),
        "stream": {},
        "conditions": [list(o) for o in offsets],
        "stages": [{"name": "stream", "last_condition": conditions - 1}],
    }
    run_folder = RunFolder(folder)
    run_folder.start(config, urdf_text)
    replay, g, size = ReplayBuffer(run_folder.replay_path), torch.Generator().manual_seed(0), 0
    for index, offset in enumerate(offsets):
        samples = random_samples(trajectories, T, layout.dX, layout.dU, g)
        replay.append_condition(index, offset, samples, iterations=10)
        size += sum(t.numel() * t.element_size() for t in samples if t is not None)
    return size


def show(name: str, report: ExportReport, raw_bytes: int) -> None:
    s = report.seconds
    print(
        f"{name:7s} {report.trajectories} trajectories, {report.steps} steps in {s:.2f} s: "
        f"{raw_bytes / 1e6 / s:6.1f} MB/s, {report.trajectories / s:6.1f} trajectories/s "
        f"({report.megabytes:.1f} MB on disk)"
    )


def main() -> None:
    args = parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "run"
        layout = StateLayout(load_arm(URDF).dof)
        raw = make_run(folder, layout, args.conditions, args.trajectories, args.T)
        print(f"synthetic replay: {raw / 1e6:.1f} MB of arrays")
        show("hdf5", export_hdf5(folder, Path(tmp) / "dataset.h5"), raw)
        # The Minari episodes hold states, actions and rewards only.
        N = args.conditions * args.trajectories
        minari_raw = N * args.T * (layout.dX + layout.dU + 1) * 8
        show("minari", export_minari(folder, Path(tmp) / "minari" / "peg-bench-v0"), minari_raw)
        start = time.perf_counter()
        load_dataset(Path(tmp) / "dataset.h5")
        seconds = time.perf_counter() - start
        print(f"load    {N} trajectories in {seconds:.2f} s: {raw / 1e6 / seconds:6.1f} MB/s")


if __name__ == "__main__":
    run(main)
