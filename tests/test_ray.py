"""On a local two-CPU Ray instance, one for the module: a CI-sized sweep (a cell finishes, a
cell that fails is retried and reported, a rerun skips the finished cell) and an
evaluation whose actors give the process pool's results; and, with a stand-in for the ray
module, when a connection starts and stops an instance of its own. The tests on the instance
are marked slow (Ray's start-up)."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from test_evaluation import fabricate_run
from test_sweep import KUKA, TINY

from lolgps_torch import sweep
from lolgps_torch.cluster import ray_connection
from lolgps_torch.errors import LolgpsError
from lolgps_torch.evaluation.areas import AreaConfig
from lolgps_torch.evaluation.evaluate import evaluate_run


class _FakeRay(SimpleNamespace):
    """What :func:`ray_connection` calls on the ray module, recorded."""

    def __init__(self, running: bool, fails: bool = False) -> None:
        super().__init__(running=running, fails=fails, calls=[])

    def is_initialized(self) -> bool:
        return bool(self.running)

    def init(self, address: str | None = None, **options: Any) -> None:
        self.calls.append(("init", address, options.get("num_cpus")))
        if self.fails:
            raise ConnectionError("Could not find any running Ray instance.\nPlease start one")
        self.running = True

    def cluster_resources(self) -> dict[str, float]:
        return {"CPU": 3.0}

    def shutdown(self) -> None:
        self.calls.append(("shutdown",))
        self.running = False


def test_a_connection_stops_only_the_instance_it_started() -> None:
    fresh = _FakeRay(running=False)
    with ray_connection(fresh, None, 2) as slots:  # type: ignore[arg-type]
        assert slots == 3 and fresh.running
    assert fresh.calls == [("init", None, 2), ("shutdown",)] and not fresh.running
    running = _FakeRay(running=True)
    with ray_connection(running, "auto", 2):  # type: ignore[arg-type]
        pass
    assert running.calls == [] and running.running  # used as it is, left running
    absent = _FakeRay(running=False, fails=True)
    with (
        pytest.raises(
            LolgpsError, match="^cannot start the Ray cluster at auto: Please start one$"
        ),
        ray_connection(absent, "auto", 2),  # type: ignore[arg-type]
    ):
        pass
    assert absent.calls == [("init", "auto", None)]


@pytest.fixture(scope="module")
def local_ray() -> Iterator[None]:
    """A local Ray instance with two CPUs for this module, shut down at its end. Its workers
    run at the tests' own priority: at Ray's default niceness (15) the sweep's runs got a few
    per cent of a core beside the other tests and took minutes."""
    ray = pytest.importorskip("ray")
    import logging

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RAY_worker_niceness", "0")
        ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.ERROR)
    try:
        yield
    finally:
        ray.shutdown()


@pytest.fixture(scope="module")
def conditions(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One training position: the smallest stream."""
    path = tmp_path_factory.mktemp("conditions") / "one.json"
    path.write_text("[[0.02, 0.02]]")
    return path


@pytest.mark.slow  # Ray's start-up and its workers': a minute or more on a loaded machine
def test_a_sweep_finishes_a_cell_retries_a_failing_one_and_a_rerun_skips_the_finished(
    local_ray: None, conditions: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "broken_arm.urdf"
    broken.write_text("<robot name='broken'>")  # exists for the grid check; run_stream rejects it
    out = tmp_path / "sweep"
    argv = ["--urdf", KUKA, str(broken), "--conditions", str(conditions), "--out", str(out)]
    assert sweep.main([*argv, "--", *TINY]) == 1
    captured = capsys.readouterr()
    assert "0 finished before (skipped), 0 to resume, 0 to evaluate, 2 new" in captured.out
    assert "[1/2 done, 0 running, 1 failed" in captured.out
    assert "lolgps-broken_arm-paper-seed0 failed (error: " in captured.out  # the first attempt
    assert "lolgps-broken_arm-paper-seed0 FAILED: error: " in captured.out
    assert "lolgps-broken_arm-paper-seed0: error: " in captured.err
    log = (out / "lolgps-broken_arm-paper-seed0" / sweep.LOG_FILE).read_text()
    assert log.count("$ ") == 2  # tried twice
    statuses = {c["name"]: c for c in json.loads((out / "sweep.json").read_text())["cells"]}
    assert statuses["lolgps-kuka_peg-paper-seed0"]["status"] == "finished"
    assert statuses["lolgps-broken_arm-paper-seed0"]["status"] == "failed"
    assert statuses["lolgps-broken_arm-paper-seed0"]["error"].startswith("error: ")
    summary = (out / "summary.md").read_text()
    assert "| lolgps | kuka_peg | paper | 1 |" in summary
    assert "`lolgps-broken_arm-paper-seed0`: error: " in summary
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert len(rows) == 1 and rows[0]["seeds"] == "1"
    # 1 iteration x 2 samples: the controller planned on the model succeeds at once
    assert float(rows[0]["rollouts_mean"]) == 2.0

    finished = out / "lolgps-kuka_peg-paper-seed0" / "summary.json"
    mtime = finished.stat().st_mtime_ns
    rerun = ["--urdf", KUKA, "--conditions", str(conditions), "--out", str(out), "--", *TINY]
    assert sweep.main(rerun) == 0
    assert (
        "1 finished before (skipped), 0 to resume, 0 to evaluate, 0 new" in capsys.readouterr().out
    )
    assert finished.stat().st_mtime_ns == mtime
    recorded = json.loads((out / "sweep.json").read_text())
    assert [c["status"] for c in recorded["cells"]] == ["skipped"]


@pytest.mark.slow  # its actors' start-up on a loaded machine: a minute
def test_evaluation_on_ray_equals_the_process_pool(local_ray: None, tmp_path: Path) -> None:
    """``ray="local"`` with an instance running: its actors run the jobs, give the process
    pool's results, and the instance is left running."""
    import ray

    run = tmp_path / "run"
    fabricate_run(run)
    areas = AreaConfig(n_areas=1, positions_per_area=3)
    pool = evaluate_run(run, workers=1, areas=areas, batch_size=2)
    on_ray = evaluate_run(run, workers=2, areas=areas, batch_size=2, ray="local")
    assert on_ray["stages"] == pool["stages"]
    assert ray.is_initialized()
