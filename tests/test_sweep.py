"""The sweep without Ray: grid parsing and input checks, and the mean ± sd aggregation on
hand-made run folders (test_ray.py runs sweeps)."""

from __future__ import annotations

import csv
import io
import json
import math
import statistics
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import ScriptRun

from lolgps_torch import sweep
from lolgps_torch.errors import LolgpsError

ROOT = Path(__file__).resolve().parents[1]
KUKA = str(ROOT / "robots" / "kuka_peg.urdf")
TINY = ["--max-iterations", "2", "--success-phases", "1", "--distill-steps", "50", "--samples", "2"]


def _sweep(tmp: Path, *argv: str) -> sweep.Sweep:
    """A validated sweep from a command line, its --out under ``tmp`` unless given."""
    own, extra = sweep.split_extra(argv)
    if "--out" not in own:
        own += ["--out", str(tmp / "out")]
    return sweep.make_sweep(sweep.build_parser().parse_args(own), extra)


# -- the grid and input checks -------------------------------------------------------------


def test_seeds_accept_ranges_lists_and_commas() -> None:
    assert sweep.parse_seeds(["0-2"]) == [0, 1, 2]
    assert sweep.parse_seeds(["0", "1", "5"]) == [0, 1, 5]
    assert sweep.parse_seeds(["3,0-1", "1"]) == [3, 0, 1]


@pytest.mark.parametrize("tokens", [["2-1"], ["x"], ["-1"], ["1-"], [""], []])
def test_bad_seeds_are_user_errors(tokens: list[str]) -> None:
    with pytest.raises(LolgpsError, match="--seeds"):
        sweep.parse_seeds(tokens)


def test_grid_is_methods_x_arms_x_streams_x_seeds_with_readable_names() -> None:
    cells = sweep.make_grid([0, 1], ["naive", "lolgps"], ["/a/kuka.urdf", "b/ur5.urdf"], ["paper"])
    assert len(cells) == 8
    assert cells[0].name == "naive-kuka-paper-seed0"
    assert cells[1].name == "naive-kuka-paper-seed1"
    assert cells[-1].name == "lolgps-ur5-paper-seed1"
    assert len({c.name for c in cells}) == 8


@pytest.mark.parametrize(
    ("methods", "urdfs", "streams", "message"),
    [
        (["gps"], ["a.urdf"], ["paper"], "unknown method 'gps'"),
        (["lolgps"], ["a.urdf"], ["other"], "unknown stream 'other'"),
        (["lolgps"], ["x/a.urdf", "y/a.urdf"], ["paper"], "different names"),
    ],
)
def test_grid_rejects_unknown_methods_streams_and_clashing_arms(
    methods: list[str], urdfs: list[str], streams: list[str], message: str
) -> None:
    with pytest.raises(LolgpsError, match=message):
        sweep.make_grid([0], methods, urdfs, streams)


def test_extra_flags_split_at_the_first_double_dash() -> None:
    assert sweep.split_extra(["--seeds", "0", "--", "--samples", "2", "--", "x"]) == (
        ["--seeds", "0"],
        ["--samples", "2", "--", "x"],
    )
    assert sweep.split_extra(["--seeds", "0"]) == (["--seeds", "0"], [])


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--methods", "lolgps", "gps"], "unknown method"),
        (["--urdf", "no/such.urdf"], "no such file"),
        (["--seeds", "3-1"], "the range is empty"),
        (["--stream", "other"], "invalid choice"),
        (["--num-cpus", "0"], "must be >= 1"),
        (["--address", "auto", "--num-cpus", "2"], "drop it with --address"),
        (["--address", "nohost"], "expected auto or HOST:PORT"),
        (["--address", "127.0.0.1:1"], "no Ray head answers"),
        (["--evaluate-args=--areas 2"], "needs --evaluate"),
        (["--evaluate", "--evaluate-args=--workers 3"], "sets --workers"),
        (["--", "--seed", "3"], "sets --seed"),
        (["--", "--out=x"], "sets --out"),
        (["--", "--res"], "sets --resume"),
    ],
)
def test_bad_input_is_a_user_error_before_any_work(
    tmp_path: Path, argv: list[str], message: str
) -> None:
    with pytest.raises(LolgpsError, match=message):
        _sweep(tmp_path, *argv)
    assert not (tmp_path / "out").exists()


def test_conditions_file_and_out_folder_are_checked(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"not": "a list"}')
    with pytest.raises(LolgpsError, match="--conditions"):
        _sweep(tmp_path, "--conditions", str(bad))
    with pytest.raises(LolgpsError, match="--conditions"):
        _sweep(tmp_path, "--conditions", str(tmp_path / "missing.json"))
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(LolgpsError, match="not a folder"):
        _sweep(tmp_path, "--out", str(blocker))
    with pytest.raises(LolgpsError, match="cannot write"):
        _sweep(tmp_path, "--out", str(blocker / "below"))


def test_a_valid_sweep_resolves_paths_and_builds_commands(tmp_path: Path) -> None:
    conditions = tmp_path / "c.json"
    conditions.write_text("[[0.02, 0.02]]")
    s = _sweep(tmp_path, "--seeds", "0-1", "--conditions", str(conditions), "--", *TINY)
    assert [c.name for c in s.cells] == [
        "lolgps-kuka_peg-paper-seed0",
        "lolgps-kuka_peg-paper-seed1",
    ]
    assert Path(s.plan.out).is_absolute() and Path(s.cells[0].urdf).is_absolute()
    command = sweep.stream_command(s.cells[1], s.plan, resume=True)
    assert command[:4] == [sys.executable, "-m", "lolgps_torch", "run"]  # no script path
    out = command[command.index("--out") + 1]
    assert out == str(Path(s.plan.out) / "lolgps-kuka_peg-paper-seed1")
    assert command[-len(TINY) - 1 : -1] == TINY and command[-1] == "--resume"
    assert "--stream" not in command  # the paper stream is the run's default
    assert "--resume" not in sweep.stream_command(s.cells[0], s.plan, resume=False)
    evaluate = sweep.evaluate_command(s.cells[0], s.plan)
    assert evaluate[:4] == [sys.executable, "-m", "lolgps_torch", "evaluate"]
    assert evaluate[-4:] == ["--run", str(Path(s.plan.out) / s.cells[0].name), "--workers", "1"]


def test_variants_run_each_cell_once_per_flag_set(tmp_path: Path) -> None:
    variants = tmp_path / "v.json"
    variants.write_text(json.dumps({"payload": "--payload 1 --plant-seed 2", "gmm+1": ""}))
    s = _sweep(tmp_path, "--seeds", "0-1", "--variants", str(variants), "--", *TINY)
    assert [c.name for c in s.cells] == [
        "lolgps-kuka_peg-paper-payload-seed0",
        "lolgps-kuka_peg-paper-payload-seed1",
        "lolgps-kuka_peg-paper-gmm+1-seed0",
        "lolgps-kuka_peg-paper-gmm+1-seed1",
    ]
    command = sweep.stream_command(s.cells[1], s.plan, resume=False)
    assert command[-len(TINY) - 4 :] == [*TINY, "--payload", "1", "--plant-seed", "2"]
    assert sweep.stream_command(s.cells[2], s.plan, resume=False)[-len(TINY) :] == TINY


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[1, 2]", "expected a JSON object"),
        ("{}", "expected a JSON object"),
        ("{not json", "not JSON"),
        ('{"a-b": "--payload 1"}', "may use only"),
        ('{"a": ["--payload", "1"]}', "must be one string"),
        ('{"a": "--seed 3"}', "sets --seed"),
        ('{"a": "--payload \'1"}', "quotation"),
    ],
)
def test_bad_variants_files_are_user_errors(tmp_path: Path, text: str, message: str) -> None:
    variants = tmp_path / "v.json"
    variants.write_text(text)
    with pytest.raises(LolgpsError, match=message):
        _sweep(tmp_path, "--variants", str(variants))
    with pytest.raises(LolgpsError, match="--variants"):
        _sweep(tmp_path, "--variants", str(tmp_path / "missing.json"))
    assert not (tmp_path / "out").exists()


def test_cell_state_follows_the_files_in_the_folder(tmp_path: Path) -> None:
    assert sweep.cell_state(tmp_path, evaluate=False) == "new"
    (tmp_path / "config.json").write_text("{}")
    assert sweep.cell_state(tmp_path, evaluate=False) == "resume"
    (tmp_path / "summary.json").write_text("{}")
    assert sweep.cell_state(tmp_path, evaluate=False) == "done"
    assert sweep.cell_state(tmp_path, evaluate=True) == "evaluate"
    (tmp_path / "eval.json").write_text("{}")
    assert sweep.cell_state(tmp_path, evaluate=True) == "done"


def test_error_line_is_the_last_error_line() -> None:
    stderr = "warning: x\nerror: first\nTraceback\nerror: the reason\nmore\n"
    assert sweep.error_line(stderr, 2) == "error: the reason"
    assert sweep.error_line("usage: run_stream.py\nrun_stream.py: error: bad flag\n", 2) == (
        "run_stream.py: error: bad flag"
    )
    assert sweep.error_line("Traceback\n  File x\nValueError: boom\n", 1) == "ValueError: boom"
    assert sweep.error_line("", -9) == "killed by signal 9"
    assert sweep.error_line("", 3) == "exit status 3"


def test_without_ray_the_error_names_the_install_command(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(LolgpsError, match=r"pip install -e '\.\[ray\]'"):
        sweep.main(["--out", str(tmp_path / "out")])


def test_script_prints_one_error_line_and_exits_2(
    tmp_path: Path, run_script: Callable[..., ScriptRun]
) -> None:
    result = run_script("scripts/sweep.py", "--seeds", "x", "--out", str(tmp_path / "o"))
    assert result.code == 2
    assert result.err.startswith("error: --seeds 'x'") and result.err.count("\n") == 1


def test_progress_counts_cells_and_estimates_the_rest() -> None:
    stream = io.StringIO()
    progress = sweep.Progress(total=4, done=1, slots=2, stream=stream)
    cell = sweep.Cell("lolgps", "/a/kuka.urdf", "paper", 0)
    progress.end(sweep.Outcome(cell, "finished", wall_time=30.0), pending=2)
    progress.end(sweep.Outcome(cell, "failed", "error: boom"), pending=1)
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("[2/4 done, 2 running, 0 failed, ETA ")
    assert lines[0].endswith("lolgps-kuka-paper-seed0 finished in 30s")
    assert lines[1].startswith("[2/4 done, 1 running, 1 failed, ETA ")
    assert lines[1].endswith("FAILED: error: boom")
    assert [sweep.format_duration(s) for s in (42, 185, 3720, None)] == [
        "42s",
        "3m05s",
        "1h02m",
        "?",
    ]


# -- aggregation on hand-made run folders --------------------------------------------------


def _fake_run(
    folder: Path, success: list[bool], iterations: list[int], samples: int, **extra: Any
) -> None:
    """A finished run folder: summary.json, config.json, and optionally eval.json and the
    sweep's wall time (``evaluation`` = (average final success, forgetting per area),
    ``wall_time``)."""
    folder.mkdir(parents=True)
    entries = [
        {"condition": c, "offset": [0.0, 0.0], "iterations": n, "first_success_iteration": None,
         "policy_final_distance_end": math.nan, "policy_success_end": ok}
        for c, (ok, n) in enumerate(zip(success, iterations, strict=True))
    ]  # fmt: skip
    (folder / "summary.json").write_text(json.dumps({"conditions": entries}))
    (folder / "config.json").write_text(json.dumps({"stream": {"local": {"samples": samples}}}))
    if "evaluation" in extra:
        average, per_area = extra["evaluation"]
        defined = [v for v in per_area if v is not None]
        forgetting = {"per_area": per_area, "mean": statistics.fmean(defined)}
        metrics = {"average_final_success": average, "forgetting": {"success_rate": forgetting}}
        (folder / "eval.json").write_text(json.dumps({"metrics": metrics}))
    if "wall_time" in extra:
        (folder / sweep.CELL_FILE).write_text(json.dumps({"wall_time": extra["wall_time"]}))


@pytest.fixture
def fake_sweep(tmp_path: Path) -> sweep.Sweep:
    """lolgps seeds 0-2 (seed 2 failed: no summary) and naive seed 0, on one arm."""
    out = tmp_path / "sweep"
    cells = sweep.make_grid([0, 1, 2], ["lolgps", "naive"], ["/r/kuka.urdf"], ["paper"])
    _fake_run(out / "lolgps-kuka-paper-seed0", [True, False], [3, 5], 5,
              evaluation=(0.8, [0.1, None, 0.0]), wall_time=100.0)  # fmt: skip
    _fake_run(out / "lolgps-kuka-paper-seed1", [True, True], [2, 2], 5,
              evaluation=(0.6, [0.3, None, 0.2]), wall_time=140.0)  # fmt: skip
    (out / "lolgps-kuka-paper-seed2").mkdir()
    (out / "lolgps-kuka-paper-seed2" / "config.json").write_text("{}")
    _fake_run(out / "naive-kuka-paper-seed0", [False, True, False, False], [4, 4, 4, 4], 2)
    plan = sweep.Plan(out=str(out), cwd=".", conditions=None, evaluate=True)
    return sweep.Sweep(cells, plan, None, 2)


def test_cell_metrics_read_the_run_files(fake_sweep: sweep.Sweep) -> None:
    row = sweep.cell_metrics(Path(fake_sweep.plan.out) / "lolgps-kuka-paper-seed0")
    assert row == {
        "train_success": 0.5,
        "test_success": 0.8,
        "forgetting_area0": 0.1,
        "forgetting_areas": pytest.approx(0.05),
        "rollouts": 40.0,  # (3 + 5) iterations x 5 samples
        "wall_time": 100.0,
    }
    assert sweep.cell_metrics(Path(fake_sweep.plan.out) / "lolgps-kuka-paper-seed2") is None


def test_aggregate_is_mean_and_sample_sd_over_finished_seeds(fake_sweep: sweep.Sweep) -> None:
    lolgps, naive = sweep.aggregate(fake_sweep.cells, Path(fake_sweep.plan.out))
    assert (lolgps["method"], lolgps["arm"], lolgps["stream"], lolgps["seeds"]) == (
        "lolgps", "kuka", "paper", 2
    )  # fmt: skip
    assert lolgps["train_success_mean"] == pytest.approx(0.75)
    assert lolgps["train_success_sd"] == pytest.approx(math.sqrt(0.125))  # |1 - 0.5| / sqrt(2)
    assert lolgps["test_success_mean"] == pytest.approx(0.7)
    assert lolgps["test_success_sd"] == pytest.approx(0.2 / math.sqrt(2))
    assert lolgps["forgetting_area0_mean"] == pytest.approx(0.2)
    assert lolgps["rollouts_mean"] == pytest.approx(30.0)  # 40 and 20
    assert lolgps["rollouts_sd"] == pytest.approx(20.0 / math.sqrt(2))
    assert lolgps["wall_time_mean"] == pytest.approx(120.0)
    assert naive["seeds"] == 1 and naive["train_success_mean"] == 0.25
    assert naive["train_success_sd"] is None  # undefined for one seed
    assert naive["rollouts_mean"] == 32.0
    assert naive["test_success_mean"] is None and naive["test_success_n"] == 0


def test_mean_sd_skips_missing_and_nan_values() -> None:
    assert sweep.mean_sd([1.0, None, math.nan, 3.0]) == (2.0, pytest.approx(math.sqrt(2)), 2)
    assert sweep.mean_sd([None]) == (None, None, 0)
    assert sweep.format_mean_sd(0.5, 0.25, ".2f") == "0.50 ± 0.25"
    assert sweep.format_mean_sd(0.1, 0.05, "+.2f") == "+0.10 ± 0.05"
    assert sweep.format_mean_sd(3.0, None, ".0f") == "3"
    assert sweep.format_mean_sd(None, None, ".2f") == "-"


def test_summaries_are_written_as_markdown_csv_and_figure(fake_sweep: sweep.Sweep) -> None:
    failed = [sweep.Outcome(fake_sweep.cells[2], "failed", "error: boom")]
    written = sweep.write_summaries(fake_sweep, failed)
    out = Path(fake_sweep.plan.out)
    assert written == [out / "summary.md", out / "summary.csv", out / "summary.png"]
    markdown = (out / "summary.md").read_text()
    assert "| lolgps | kuka | paper | 2 | 0.75 ± 0.35 | 0.70 ± 0.14 |" in markdown
    assert "| naive | kuka | paper | 1 | 0.25 | - |" in markdown
    assert "`lolgps-kuka-paper-seed2`: error: boom" in markdown
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["method"] for r in rows] == ["lolgps", "naive"]
    assert float(rows[0]["rollouts_mean"]) == 30.0 and rows[1]["train_success_sd"] == ""
    assert (out / "summary.png").stat().st_size > 0


def test_variants_are_aggregated_apart(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    cells = sweep.make_grid([0], ["lolgps"], ["/r/kuka.urdf"], ["paper"], ["a", "b"])
    _fake_run(out / "lolgps-kuka-paper-a-seed0", [True, True], [2, 2], 5)
    _fake_run(out / "lolgps-kuka-paper-b-seed0", [True, False], [2, 4], 5)
    plan = sweep.Plan(out=str(out), cwd=".", conditions=None, evaluate=False)
    rows = sweep.aggregate(cells, out)
    assert [(r["variant"], r["train_success_mean"], r["rollouts_mean"]) for r in rows] == [
        ("a", 1.0, 20.0),
        ("b", 0.5, 30.0),
    ]
    sweep.write_summaries(sweep.Sweep(cells, plan, None, 1), [])
    markdown = (out / "summary.md").read_text()
    assert "| method | arm | stream | variant | seeds |" in markdown
    assert "| lolgps | kuka | paper | b | 1 | 0.50 |" in markdown


def test_the_plant_table_reads_a_sweep_of_plants_and_learners(
    tmp_path: Path, run_script: Callable[..., Any]
) -> None:
    """scripts/research/plant_table.py: its variants are ``<plant>.<learner>`` flag sets a sweep
    accepts, and its table gives per arm, plant and learner the positions per seed, the worst
    local controller, the means of rollouts, first success and repair rounds, and the payload
    identified after the first condition with the one-step errors of its model and the true
    arm's."""
    script = "scripts/research/plant_table.py"
    listed = run_script(script, "variants", "--plants", "urdf", "payload")
    variants = json.loads(listed.out)
    assert variants == {
        "urdf.model": "",
        "urdf.identified": "--identify",
        "urdf.gmm": "--dynamics-prior gmm",
        "payload.model": "--payload 1 --gravity-compensation model",
        "payload.identified": "--payload 1 --gravity-compensation model --identify",
        "payload.gmm": "--payload 1 --gravity-compensation model --dynamics-prior gmm",
    }
    assert len(json.loads(run_script(script, "variants").out)) == 7 * 3  # the table's plants
    path = tmp_path / "variants.json"
    path.write_text(listed.out)
    s = _sweep(tmp_path, "--seeds", "0-1", "--variants", str(path))
    assert len(s.cells) == 12
    out = Path(s.plan.out)
    cells = [
        {"name": c.name, "arm": c.arm, "variant": c.variant, "seed": c.seed}
        for c in s.cells
        if c.variant in ("urdf.model", "payload.identified")
    ]
    (out / "sweep.json").write_text(json.dumps({"cells": cells}))

    def finished(name: str, positions: list[bool], worst: float, identified: float | None) -> None:
        entries = [
            {"policy_success_end": ok, "local_final_distance": worst / (c + 1), "rollouts": 10,
             "first_success_iteration": c, "repairs": 2}
            for c, ok in enumerate(positions)
        ]  # fmt: skip
        (out / name).mkdir()
        (out / name / "summary.json").write_text(json.dumps({"conditions": entries}))
        if identified is None:
            return
        record = {"event": "identified", "condition": 1, "payload": identified,
                  "error_identified": 0.03, "error_plant": 0.02}  # fmt: skip
        (out / name / "metrics.jsonl").write_text(json.dumps(record) + "\n")

    finished("lolgps-kuka_peg-paper-urdf.model-seed0", [True, True], 0.002, None)
    finished("lolgps-kuka_peg-paper-payload.identified-seed0", [True, False], 0.004, 0.98)
    finished("lolgps-kuka_peg-paper-payload.identified-seed1", [True, True], 0.010, 1.01)
    table = run_script(script, "table", str(out)).out.splitlines()
    assert table[2] == "| kuka_peg | the URDF | URDF model | 1 | 2/2 | 0.002 | 20 | 0.5 | 4.0 | – |"
    assert table[3] == (
        "| kuka_peg | +1 kg, compensated by the URDF | identified | 2 | 1/2, 2/2 | 0.010 | 20 | "
        "0.5 | 4.0 | 0.980, 0.0300 / 0.0200; 1.010, 0.0300 / 0.0200 |"
    )
    assert len(table) == 4  # cells without a finished run are left out
    assert run_script(script, "table", str(out), str(out)).out.splitlines() == table  # once
    assert run_script(script, "table", str(tmp_path)).code == 2
