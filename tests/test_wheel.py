"""A non-editable install works: the wheel built from this tree (offline, no build isolation)
holds the default arm as package data, and the Gym environment made from the installed
package alone, outside the source tree, resets."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECK = """
import gymnasium as gym
import lolgps_torch
from lolgps_torch.gym_env import DEFAULT_URDF
env = gym.make("lolgps_torch/PegInsertion-v0")
observation, _ = env.reset(seed=0)
env.close()
print(lolgps_torch.__file__)
print(DEFAULT_URDF)
print(observation.shape)
"""


def _pip(*args: str) -> None:
    cmd = [sys.executable, "-m", "pip", *args, "--no-deps", "--no-index", "-q"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.mark.slow  # a wheel built and installed; .ci/run's wheel environment runs its commands
def test_the_installed_wheel_makes_and_resets_the_env(tmp_path: Path) -> None:
    source = tmp_path / "source"  # a copy, so the build leaves nothing in the tree
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source)
    shutil.copytree(
        ROOT / "lolgps_torch", source / "lolgps_torch", ignore=shutil.ignore_patterns("__pycache__")
    )
    _pip("wheel", "--no-build-isolation", "-w", str(tmp_path / "dist"), str(source))
    (wheel,) = (tmp_path / "dist").glob("lolgps_torch-*.whl")
    site = tmp_path / "site"
    _pip("install", "--target", str(site), str(wheel))
    shutil.rmtree(source)

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    proc = subprocess.run(
        [sys.executable, "-c", CHECK],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=elsewhere,
        env={**os.environ, "PYTHONPATH": str(site)},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    package, urdf, shape = proc.stdout.strip().splitlines()[-3:]
    assert package == str(site / "lolgps_torch" / "__init__.py")
    assert urdf == str(site / "lolgps_torch" / "robot" / "data" / "kuka_peg.urdf")
    assert shape == "(26,)"
