"""The model-free baseline: stable-baselines3 accepts the normalised env, and a CI-sized run of
scripts/research/sb3_baseline.py writes its result, figure and GPS comparison."""

from __future__ import annotations

import importlib.util
import json
import runpy
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import pytest

from lolgps_torch.gym_env import NORMALIZED_ENV_ID

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "research" / "sb3_baseline.py"


def run_script(args: list[str], monkeypatch: pytest.MonkeyPatch) -> int:
    """Run the baseline script in this process; its exit status."""
    monkeypatch.setattr(sys, "argv", ["sb3_baseline.py", *args])
    try:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    except SystemExit as exit_info:
        return int(exit_info.code or 0)
    return 0


def test_sb3_checker_accepts_the_normalized_env() -> None:
    env_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env = gym.make(NORMALIZED_ENV_ID)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env_checker.check_env(env.unwrapped)
    env.close()
    assert [str(w.message) for w in caught] == []


def test_sac_smoke_run_writes_result_and_figure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """200 steps (2 episodes of T = 100, 100 gradient steps) of SAC next to a GPS run of two
    iterations whose second succeeded."""
    pytest.importorskip("stable_baselines3")
    gps = tmp_path / "gps"
    gps.mkdir()
    (gps / "summary.json").write_text(
        json.dumps({"iterations": 2, "noiseless_final_distance": 0.01})
    )
    times = {"time_sample": 1.0, "time_fit": 0.5, "time_cstep": 0.25}
    rows = [
        {"iteration": i, "mean_distance": d, "best_distance": d, "success_rate": r, **times}
        for i, (d, r) in enumerate([(0.3, 0.0), (0.05, 0.6)])
    ]
    (gps / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "sac"
    args = ["--steps", "200", "--gps", str(gps), "--out", str(out), "--every", "1"]
    args += ["--limits", "off"]  # random full-effort torques pass the limits at once
    assert run_script(args, monkeypatch) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["steps"] == 200 and result["rollouts"] == 2
    assert [e["steps"] for e in result["episodes"]] == [100, 200]
    assert result["gps"]["rollouts"] == 10 and result["gps"]["rollouts_to_first_success"] == 10
    assert result["gps"]["seconds"] == pytest.approx(3.5)
    assert set(result["deterministic_policy"]) == {"final_distance", "success"}
    assert (out / "learning_curve.png").stat().st_size > 0


def test_without_sb3_one_error_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == "stable_baselines3" else find_spec(name, *a),
    )
    assert run_script(["--out", str(tmp_path / "out")], monkeypatch) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: stable-baselines3 is not installed: pip install 'lolgps_torch[sb3]'"]
    assert not (tmp_path / "out").exists()
