"""The Fig. 4 evaluation: area geometry, the statistics against hand-computed answers, the plot,
and one small evaluation of a fabricated run folder (deterministic, independent of workers)."""

from __future__ import annotations

import itertools
import json
import math
import multiprocessing
import multiprocessing.spawn
import runpy
import shutil
import statistics
import subprocess
import sys
import types
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest
import torch

from lolgps_torch.data.checkpoint import save_policy
from lolgps_torch.data.run_folder import RunFolder, portable_urdf, task_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation import jobs as jobs_module
from lolgps_torch.evaluation.areas import (
    AreaConfig,
    area_centres,
    area_of,
    default_training_stream,
    sample_area_positions,
)
from lolgps_torch.evaluation.evaluate import evaluate_run
from lolgps_torch.evaluation.jobs import run_jobs
from lolgps_torch.evaluation.metrics import (
    aggregate,
    average_final_success,
    bootstrap_mean_ci,
    first_training_stage,
    forgetting,
    mean_defined,
    wilson_interval,
)
from lolgps_torch.evaluation.plot import plot_fig4
from lolgps_torch.evaluation.square import SquareConfig
from lolgps_torch.evaluation.table import format_table, markdown_table
from lolgps_torch.evaluation.worker import Job, PolicyState, RolloutSetup, run_worker
from lolgps_torch.policy.net import GaussianPolicy
from lolgps_torch.sim.pool import main_script_hidden
from lolgps_torch.task import PegTask, TaskConfig

KUKA = "robots/kuka_peg.urdf"
SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "evaluate.py"
STAGES = [
    {"name": "train0", "last_condition": 3},
    {"name": "train1", "last_condition": 5},
    {"name": "train2", "last_condition": 7},
]

# -- areas --------------------------------------------------------------------------------


def test_area_centres_lie_along_the_lateral_axis() -> None:
    centres = area_centres(AreaConfig())
    expected = torch.tensor([[0.0, 0.05 * k] for k in range(7)], dtype=torch.float64)
    assert torch.allclose(centres, expected, atol=1e-15)
    along_x = area_centres(AreaConfig(n_areas=3, spacing=0.1, axis="x"))
    assert torch.allclose(along_x, torch.tensor([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]]).double())


def test_area_positions_are_inside_their_discs_and_deterministic() -> None:
    config = AreaConfig()
    positions = sample_area_positions(config)
    assert positions.shape == (7, 50, 2)
    radial = (positions - area_centres(config)[:, None]).norm(dim=-1)
    assert bool((radial <= config.radius).all())
    assert float(radial.max()) > 0.8 * config.radius  # spread over the disc, not a point
    assert torch.equal(positions, sample_area_positions(config))
    assert not torch.equal(positions, sample_area_positions(AreaConfig(seed=1)))
    fewer = sample_area_positions(AreaConfig(n_areas=3))
    assert torch.equal(fewer, positions[:3])  # adding areas keeps earlier areas' positions


def test_area_config_rejects_bad_geometry() -> None:
    with pytest.raises(LolgpsError):
        AreaConfig(radius=0.0)
    with pytest.raises(LolgpsError):
        AreaConfig(n_areas=0)


def test_default_training_stream() -> None:
    config = AreaConfig()
    conditions, stages = default_training_stream(config, seed=3)
    assert stages == STAGES
    assert conditions[:4] == [(-0.02, -0.02), (-0.02, 0.02), (0.02, -0.02), (0.02, 0.02)]
    extra = torch.tensor(conditions[4:])
    centres = area_centres(config)
    assert bool(((extra[:2] - centres[2]).norm(dim=-1) <= config.radius).all())
    assert bool(((extra[2:] - centres[4]).norm(dim=-1) <= config.radius).all())
    assert default_training_stream(config, seed=3) == (conditions, stages)
    assert default_training_stream(config, seed=4)[0][4:] != conditions[4:]
    # train0's corners lie just outside area 0's disc but are nearest to its centre
    assert area_of(torch.tensor(conditions), config).tolist() == [0, 0, 0, 0, 2, 2, 4, 4]
    assert area_of(torch.tensor([[0.0, 0.6], [0.06, 0.0]]), config).tolist() == [-1, -1]
    two_areas = AreaConfig(n_areas=2)  # train1's positions stay in area 2, now not evaluated
    assert area_of(torch.tensor(conditions), two_areas).tolist() == [0, 0, 0, 0, -1, -1, -1, -1]


# -- metrics ------------------------------------------------------------------------------


def _exact_bootstrap_quantiles(values: list[float], confidence: float) -> tuple[float, float]:
    """The percentile interval of the exact bootstrap distribution of the mean: all n^n
    equally likely resamples enumerated."""
    means = sorted(
        sum(draw) / len(values) for draw in itertools.product(values, repeat=len(values))
    )
    tail = (1.0 - confidence) / 2.0
    return means[int(tail * len(means))], means[int((1.0 - tail) * len(means)) - 1]


def test_bootstrap_interval_matches_the_enumerated_bootstrap() -> None:
    values = [0.0004, 0.0006, 0.0009, 0.0011, 0.0141]  # 5^5 = 3125 resamples
    mean, low, high = bootstrap_mean_ci(values)
    exact_low, exact_high = _exact_bootstrap_quantiles(values, 0.95)
    assert mean == pytest.approx(0.00342)
    assert low == pytest.approx(exact_low, abs=1e-4)
    assert high == pytest.approx(exact_high, abs=1e-4)
    assert bootstrap_mean_ci(values) == (mean, low, high)  # fixed seed: the same every time
    assert bootstrap_mean_ci([2.0]) == (2.0, None, None)
    assert bootstrap_mean_ci([4.0, 4.0, 4.0]) == (4.0, 4.0, 4.0)
    with pytest.raises(LolgpsError, match="mean of no values"):
        bootstrap_mean_ci([])


def test_bootstrap_interval_of_small_distances_stays_non_negative() -> None:
    """Small positive distances with one miss: m +- t s/sqrt(n) reaches below zero
    ([-0.0040, 0.0108] here), the bootstrap interval stays within the values' range."""
    values = [0.0004, 0.0006, 0.0009, 0.0011, 0.0141]
    half = 2.7764 * statistics.stdev(values) / math.sqrt(len(values))  # t_{0.975, 4}
    assert statistics.fmean(values) - half < 0.0
    _, low, high = bootstrap_mean_ci(values)
    assert low is not None and high is not None
    assert min(values) <= low < statistics.fmean(values) < high <= max(values)


def test_bootstrap_interval_of_many_values_is_the_normal_interval() -> None:
    """For n = 400 the mean is close to normal: m +- 1.96 s/sqrt(n) (central limit theorem)."""
    values = torch.randn(400, generator=torch.Generator().manual_seed(3)).add(5.0).tolist()
    mean, low, high = bootstrap_mean_ci(values)
    half = 1.96 * statistics.stdev(values) / math.sqrt(400)
    assert low == pytest.approx(mean - half, abs=0.1 * half)
    assert high == pytest.approx(mean + half, abs=0.1 * half)


def test_wilson_interval() -> None:
    p, low, high = wilson_interval(8, 10)  # 8/10: [0.4902, 0.9433] (Wilson 1927)
    assert p == 0.8
    assert low == pytest.approx(0.4902, abs=1e-4)
    assert high == pytest.approx(0.9433, abs=1e-4)
    assert wilson_interval(0, 10) == pytest.approx((0.0, 0.0, 0.2775), abs=1e-4)
    assert wilson_interval(10, 10) == pytest.approx((1.0, 0.7225, 1.0), abs=1e-4)


def test_aggregate_per_group() -> None:
    rows = aggregate(
        final_distance=[[0.01, 0.03], [0.2, 0.2, 0.2]],
        total_cost=[[10.0, 20.0], [5.0, 6.0, 7.0]],
        success=[[True, True], [False, True, False]],
    )
    assert [r["n"] for r in rows] == [2, 3]
    assert rows[0]["final_distance"]["mean"] == pytest.approx(0.02)
    assert rows[0]["total_cost"]["mean"] == 15.0
    # two values: the bootstrap means are 10, 15 and 20 with probabilities 1/4, 1/2, 1/4
    assert (rows[0]["total_cost"]["low"], rows[0]["total_cost"]["high"]) == (10.0, 20.0)
    assert rows[1]["final_distance"]["low"] == pytest.approx(0.2)
    assert rows[1]["success_rate"]["mean"] == pytest.approx(1 / 3)


def test_forgetting_signs_and_training_stage() -> None:
    # groups: area 0 trained by stage 0, area 1 never, area 2 by stage 1 (conditions 4, 5)
    trained = first_training_stage([0, 0, 0, 0, 2, 2, -1, 2], STAGES, n_groups=3)
    assert trained == [0, None, 1]
    distance = [[0.1, 0.5, 0.9], [0.2, 0.4, 0.05], [0.3, 0.4, 0.04]]
    assert forgetting(distance, trained, higher_is_better=False) == pytest.approx(
        [0.2, None, -0.01]  # area 0 got worse by 0.2 m; area 2 improved after its stage
    )
    success = [[0.9, 0.0, 0.0], [0.7, 0.1, 1.0], [0.5, 0.2, 0.9]]
    assert forgetting(success, trained, higher_is_better=True) == pytest.approx([0.4, None, 0.1])
    assert mean_defined([0.4, None, 0.1]) == pytest.approx(0.25)
    assert mean_defined([None]) is None
    assert average_final_success(success[-1]) == pytest.approx(1.6 / 3)


# -- plot ---------------------------------------------------------------------------------


def synthetic_evaluation() -> dict[str, Any]:
    config = AreaConfig(n_areas=4, positions_per_area=5)
    positions = sample_area_positions(config)
    groups = [
        {
            "label": f"area {k}",
            "centre": [0.0, 0.05 * k],
            "centre_distance": 0.05 * k,
            "radius": config.radius,
            "positions": positions[k].tolist(),
        }
        for k in range(4)
    ]
    stages = []
    for s, stage in enumerate(STAGES):
        distance = [[0.02 + 0.05 * k / (s + 1) + 0.001 * i for i in range(5)] for k in range(4)]
        cost = [[100.0 * (1 + d) for d in row] for row in distance]
        success = [[d < 0.06 for d in row] for row in distance]
        stages.append({**stage, "groups": aggregate(distance, cost, success)})
    conditions, _ = default_training_stream(AreaConfig(), seed=0)
    return {
        "method": "lolgps",
        "seed": 0,
        "mode": "areas",
        "area_config": asdict(config),
        "success_threshold": 0.06,
        "groups": groups,
        "stages": stages,
        "training": {"conditions": [list(c) for c in conditions], "stages": STAGES},
    }


def test_plot_writes_a_small_png(tmp_path: Path) -> None:
    path = tmp_path / "fig4.png"
    plot_fig4(synthetic_evaluation(), path)
    data = path.read_bytes()
    assert data.startswith(b"\x89PNG")
    assert 10_000 < len(data) < 200_000
    assert list(tmp_path.iterdir()) == [path]


# -- end to end on a fabricated run -------------------------------------------------------


def fabricate_run(folder: Path, method: str = "lolgps") -> None:
    """config.json (with the relative URDF path ``KUKA``), the URDF copy, summary.json and
    per-stage checkpoints of distinct untrained policies."""
    conditions, stages = default_training_stream(AreaConfig(), seed=0)
    urdf_text = portable_urdf(KUKA)
    config = {
        "task": task_json(TaskConfig(urdf=KUKA), urdf_text),
        "conditions": conditions,
        "stages": stages,
        "method": method,
        "seed": 0,
    }
    run = RunFolder(folder)
    run.start(config, urdf_text)
    for stage in stages if method != "batch" else stages[-1:]:
        policy = GaussianPolicy(26, 7)
        with torch.no_grad():
            for p in policy.parameters():
                p.mul_(0.5 + 0.2 * stage["last_condition"])
        save_policy(run.checkpoint_dir(stage["last_condition"]), policy)
    summary = [
        {"condition": c, "offset": list(o), "iterations": 3, "rollouts": 15}
        for c, o in enumerate(conditions)
    ]
    for c in range(len(conditions)):  # success rates 0, 0.5, 1 at every condition
        for i, rate in enumerate((0.0, 0.5, 1.0)):
            run.append_metrics({"condition": c, "iteration": i, "success_rate": rate})
    (folder / "summary.json").write_text(json.dumps({"conditions": summary}))


def test_evaluation_is_identical_for_one_and_two_workers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = tmp_path / "run"
    fabricate_run(run)
    areas = AreaConfig(n_areas=2, positions_per_area=2)
    one = evaluate_run(run, workers=1, areas=areas, batch_size=3, scratch=run)
    # this process claims no job, so the spawned worker runs them all
    monkeypatch.setattr(jobs_module, "next_job", lambda counter, n_jobs: None)
    two = evaluate_run(run, workers=2, areas=areas, batch_size=3)
    written = json.loads(RunFolder(run).eval_path.read_text())
    assert [s["per_position"] for s in one["stages"]] == [s["per_position"] for s in two["stages"]]
    assert one["stages"] == two["stages"] == written["stages"]
    assert [s["name"] for s in one["stages"]] == ["train0", "train1", "train2"]
    # distinct policies give distinct rollouts, so identical results are not a coincidence
    finals = [s["per_position"]["final_distance"] for s in one["stages"]]
    assert finals[0] != finals[1] != finals[2]
    assert one["metrics"]["trained_by_stage"] == ["train0", None]
    forgot = one["metrics"]["forgetting"]["final_distance"]["per_area"]
    means = [s["groups"][0]["final_distance"]["mean"] for s in one["stages"]]
    assert forgot == [pytest.approx(means[2] - means[0]), None]
    row = one["metrics"]["forward_transfer"][1]
    assert row["auc"] == pytest.approx((0.0 + 0.5 + 8 * 1.0) / 10)  # the last rate carries on
    assert row["scratch_auc"] == row["auc"] and row["forward_transfer"] == 0.0  # itself
    assert row["rollouts"] == 15 and one["metrics"]["mean_forward_transfer"] == 0.0
    assert two["metrics"]["forward_transfer"][1]["forward_transfer"] is None  # no baseline
    assert "area 1" in format_table(one)


def test_a_copied_run_folder_evaluates_alike_from_elsewhere(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run folder keeps its URDF: copied elsewhere and evaluated from another working
    directory (where its recorded relative URDF path does not exist), it gives the same
    eval.json as in place."""
    run = tmp_path / "run"
    fabricate_run(run)
    positions = [(0.0, 0.0), (0.01, -0.02)]
    evaluate_run(run, positions=positions)
    copy = tmp_path / "other" / "run"
    shutil.copytree(run, copy)
    (copy / "eval.json").unlink()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert not Path(KUKA).exists()
    evaluate_run(copy, positions=positions)
    assert (copy / "eval.json").read_text() == (run / "eval.json").read_text()


def test_positions_mode_and_batch_runs(tmp_path: Path) -> None:
    run = tmp_path / "run"
    fabricate_run(run, method="batch")
    result = evaluate_run(run, workers=1, positions=[(0.0, 0.0), (0.01, 0.1)])
    assert [s["name"] for s in result["stages"]] == ["train2"]  # batch: final checkpoint only
    assert [g["label"] for g in result["groups"]] == ["(+0.000, +0.000)", "(+0.010, +0.100)"]
    assert result["metrics"]["forgetting"] is None
    assert result["stages"][0]["groups"][0]["final_distance"]["low"] is None


def test_broken_runs_raise_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(LolgpsError, match="run folder not found"):
        evaluate_run(tmp_path / "absent")
    run = tmp_path / "run"
    fabricate_run(run)
    (run / "checkpoints" / "after_condition_005" / "policy.pt").unlink()
    with pytest.raises(LolgpsError, match="cannot load policy"):
        evaluate_run(run)
    for name in ("policy.pt", "policy.json"):
        (run / "checkpoints" / "after_condition_005" / name).unlink(missing_ok=True)
    (run / "checkpoints" / "after_condition_005").rmdir()
    with pytest.raises(LolgpsError, match="missing checkpoint for stage train1"):
        evaluate_run(run)
    (run / "config.json").write_text('{"task": {"urdf": 1}, "conditions": []')
    with pytest.raises(LolgpsError, match="corrupt"):
        evaluate_run(run)


@pytest.mark.parametrize("make", ["missing", "corrupt"])
def test_script_prints_one_error_line(
    tmp_path: Path, make: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "run"
    if make == "corrupt":
        run.mkdir()
        (run / "config.json").write_text("not json")
    monkeypatch.setattr(sys, "argv", ["evaluate.py", "--run", str(run)])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")


def test_scores_equal_those_of_the_task_itself() -> None:
    """Rollouts in a worker's worlds, scored by the main process, give what the task's own
    lockstep worlds and scoring give for the same policy and positions."""
    policy = GaussianPolicy(26, 7)
    positions = ((0.0, 0.0), (0.01, -0.02))
    config = TaskConfig(urdf=KUKA)
    [result] = run_jobs(config, [PolicyState.of("p", policy)], [Job(0, positions)], 1, 2)
    task = PegTask(config, n_worlds=2)
    try:
        with torch.no_grad():
            lockstep = task.sampler.rollout(lambda t, x, rows: policy(x), list(positions))
            samples = task.score(lockstep, list(positions))
    finally:
        task.close()
    assert result.final_distance == samples.final_distance.tolist()
    assert result.total_cost == samples.cost.sum(dim=1).tolist()
    assert result.success == samples.success.tolist()
    assert result.fault == samples.fault.tolist()


def test_a_worker_error_reaches_the_caller() -> None:
    """The worker loop run in this process: its error crosses the queue to the collector."""
    wrong = PolicyState.of("wrong", GaussianPolicy(20, 7))  # a state size the task lacks
    jobs = [Job(0, ((0.0, 0.0),))]
    task = PegTask(TaskConfig(urdf=KUKA), n_worlds=1)
    setup = RolloutSetup(
        task.arm, task.config.world, task.geometry.nominal_mouth, task.geometry.q0, 1, (wrong,)
    )
    task.close()
    context = multiprocessing.get_context("spawn")
    counter, setups, results = context.Value("q", 0), context.Queue(), context.Queue()
    setups.put(setup)
    run_worker(setups, jobs, counter, results)
    with pytest.raises(LolgpsError, match="policy maps 20 -> 7 dims"):
        list(jobs_module._collect(results, {0}, []))


WORKER_MODULES = ("lolgps_torch.evaluation.worker", "lolgps_torch.sim.pool")


def test_the_worker_imports_neither_kinematics_nor_urdf_parsing() -> None:
    """A spawned worker (an evaluation's, a stream's rollouts') imports its module and what that
    imports: none of the slow packages that only building the task needs. One new interpreter
    imports the modules one after the other, listing the slow packages loaded after each."""
    code = (
        "import importlib, sys\n"
        f"for module in {WORKER_MODULES!r}:\n"
        "    importlib.import_module(module)\n"
        "    print(module, sorted({m.split('.')[0] for m in sys.modules}"
        " & {'pytorch_kinematics', 'yourdfpy', 'trimesh'}))\n"
    )
    output = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert output.splitlines() == [f"{module} []" for module in WORKER_MODULES]


def test_spawned_workers_do_not_rerun_the_main_script(monkeypatch: pytest.MonkeyPatch) -> None:
    """multiprocessing would re-run a script started as ``python script.py`` in each worker."""
    main = types.ModuleType("__main__")
    main.__file__ = str(SCRIPT)
    monkeypatch.setitem(sys.modules, "__main__", main)
    assert "init_main_from_path" in multiprocessing.spawn.get_preparation_data("worker")
    with main_script_hidden():
        hidden = multiprocessing.spawn.get_preparation_data("worker")
    assert "init_main_from_path" not in hidden and "init_main_from_name" not in hidden
    assert main.__file__ == str(SCRIPT) and main.__spec__ is None


def test_square_test_set_is_one_group_of_held_out_positions(tmp_path: Path) -> None:
    run = tmp_path / "run"
    fabricate_run(run)
    square = SquareConfig(test_positions=4)
    evaluation = evaluate_run(run, workers=1, batch_size=4, square=(square, 3))
    assert evaluation["mode"] == "square" and len(evaluation["groups"]) == 1
    positions = evaluation["groups"][0]["positions"]
    assert len(positions) == 4 and all(abs(v) <= 0.1 for p in positions for v in p)
    training = [tuple(c) for c in evaluation["training"]["conditions"]]
    assert not {tuple(p) for p in positions} & set(training)
    assert len(evaluation["stages"][-1]["per_position"]["final_distance"][0]) == 4
    plot_fig4(evaluation, tmp_path / "fig.png")
    assert (tmp_path / "fig.png").stat().st_size > 0


def test_markdown_table_has_a_rule_and_one_line_per_row() -> None:
    table = markdown_table(("run", "policy"), [["a", "8/8"], ["b", "7/8"]])
    assert table.splitlines() == ["| run | policy |", "|---|---|", "| a | 8/8 |", "| b | 7/8 |"]
