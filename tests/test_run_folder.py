"""The run folder: atomic writes, the writability probe, the URDF copy a run keeps, config
comparison, and policy checkpoints."""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch

from lolgps_torch.data.checkpoint import load_policy, save_policy
from lolgps_torch.data.run_folder import (
    RunFolder,
    atomic_write,
    config_differences,
    evaluated_runs,
    portable_urdf,
    task_json,
)
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps import StreamConfig
from lolgps_torch.lolgps.local import LocalConfig
from lolgps_torch.lolgps.run import read_run
from lolgps_torch.policy import GaussianPolicy, PolicyConfig
from lolgps_torch.task import TaskConfig

KUKA = "robots/kuka_peg.urdf"
F64 = torch.float64


def test_policy_checkpoint_round_trip(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    config = PolicyConfig(hidden_sizes=(8, 6), steps=30, seed=4)
    policy = GaussianPolicy(3, 2, config)
    policy.set_whitening(torch.randn(20, 3, dtype=F64))
    policy.set_variance(torch.tensor([0.3, 0.7], dtype=F64))
    policy.trained = True
    save_policy(tmp_path / "ckpt", policy)
    assert sorted(p.name for p in (tmp_path / "ckpt").iterdir()) == ["policy.json", "policy.pt"]
    calls: list[dict[str, object]] = []
    real_load = torch.load

    def recording_load(*args: object, **kwargs: object) -> object:
        calls.append(kwargs)
        return real_load(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(torch, "load", recording_load)
    loaded = load_policy(tmp_path / "ckpt")
    assert [call.get("weights_only") for call in calls] == [True]
    assert loaded.config == config and loaded.trained
    x = torch.randn(7, 5, 3, dtype=F64)
    assert torch.equal(loaded(x), policy(x))
    assert torch.equal(loaded.covariance(), policy.covariance())
    assert not GaussianPolicy(3, 2, config).trained  # the flag came from the file


def test_a_corrupt_or_missing_checkpoint_is_one_error(tmp_path: Path) -> None:
    save_policy(tmp_path, GaussianPolicy(2, 1))
    (tmp_path / "policy.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(LolgpsError, match="cannot load policy from"):
        load_policy(tmp_path)
    with pytest.raises(LolgpsError, match="cannot load policy from .*missing"):
        load_policy(tmp_path / "missing")
    save_policy(tmp_path, GaussianPolicy(2, 1))
    description = json.loads((tmp_path / "policy.json").read_text())
    description["dX"] = 5  # weights of another shape
    (tmp_path / "policy.json").write_text(json.dumps(description))
    with pytest.raises(LolgpsError, match="cannot load policy from"):
        load_policy(tmp_path)


def test_a_failed_atomic_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "data.txt"
    atomic_write(path, lambda tmp: tmp.write_text("old"))

    def fail(tmp: Path) -> None:
        tmp.write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(path, fail)
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["data.txt"]


def test_the_writability_probe_leaves_nothing_behind(tmp_path: Path) -> None:
    RunFolder(tmp_path / "a" / "b").check_writable()
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "file").write_text("")
    with pytest.raises(LolgpsError, match="is not a folder"):
        RunFolder(tmp_path / "file" / "run").check_writable()
    with pytest.raises(LolgpsError, match="cannot write to /proc/nope"):
        RunFolder("/proc/nope").check_writable()


def test_the_urdf_copy_resolves_relative_meshes_from_anywhere(tmp_path: Path) -> None:
    (tmp_path / "arm" / "meshes").mkdir(parents=True)
    (tmp_path / "arm" / "meshes" / "link.obj").write_text("")
    source = tmp_path / "arm" / "arm.urdf"
    source.write_text(
        '<robot name="r"><link name="a"><visual><geometry>'
        '<mesh filename="meshes/link.obj"/></geometry></visual></link>'
        '<link name="b"><visual><geometry><mesh filename="package://missing.obj"/>'
        "</geometry></visual></link></robot>"
    )
    text = portable_urdf(str(source))
    assert f'filename="{tmp_path / "arm" / "meshes" / "link.obj"}"' in text
    assert 'filename="package://missing.obj"' in text  # not found: left as it was
    assert portable_urdf(KUKA) == Path(KUKA).read_text()  # no meshes: the text unchanged
    with pytest.raises(LolgpsError, match="cannot read URDF"):
        portable_urdf(str(tmp_path / "absent.urdf"))


def test_a_run_builds_its_task_from_its_checked_copy(tmp_path: Path) -> None:
    text = portable_urdf(KUKA)
    task = task_json(TaskConfig(urdf=KUKA), text)
    folder = RunFolder(tmp_path / "run")
    folder.start({"task": task}, text)
    assert task["urdf"] == KUKA  # the user's path, for display
    config = folder.task_config(folder.read_config()["task"])
    assert config.urdf == str(folder.urdf_path.resolve())
    assert asdict(config) == {**asdict(TaskConfig(urdf=KUKA)), "urdf": config.urdf}
    folder.urdf_path.write_text(text.replace("iiwa", "other"))
    with pytest.raises(LolgpsError, match="does not match its SHA-256"):
        folder.task_config(task)


def test_config_differences_name_every_differing_field() -> None:
    saved = {"stream": {"max_iterations": 25, "policy": {"steps": 10}}, "seed": 0}
    now = {"stream": {"max_iterations": 3, "policy": {"steps": 10}}, "seed": 0, "new": 1}
    assert config_differences(saved, now) == [
        "new: None (saved) vs 1 (now)",
        "stream.max_iterations: 25 (saved) vs 3 (now)",
    ]
    assert config_differences(saved, saved) == []


def _run(tmp_path: Path, **changes: object) -> RunFolder:
    """A run folder at ``tmp_path / "run"`` whose config.json is a one-condition run's,
    with ``changes`` to its entries."""
    text = portable_urdf(KUKA)
    config = {
        "task": task_json(TaskConfig(urdf=KUKA), text),
        "conditions": [[0.0, 0.0]],
        "stages": [{"name": "s", "last_condition": 0}],
        "method": "lolgps",
        "seed": 0,
        **changes,
    }
    folder = RunFolder(tmp_path / "run")
    folder.start(config, text)
    return folder


def test_read_run_rejects_stages_beyond_the_conditions(tmp_path: Path) -> None:
    folder = _run(tmp_path, stages=[{"name": "s", "last_condition": 1}])
    with pytest.raises(LolgpsError, match="stages must end at increasing conditions below 1"):
        read_run(folder)
    with pytest.raises(LolgpsError, match="run folder not found"):
        read_run(RunFolder(tmp_path / "absent"))


def test_stream_config_round_trips_through_config_json(tmp_path: Path) -> None:
    policy = PolicyConfig(hidden_sizes=(8, 6), pre_weight=0.5)
    stream = StreamConfig(alpha=0.2, transfer="policy", local=LocalConfig(samples=3), policy=policy)
    assert read_run(_run(tmp_path, stream=asdict(stream))).stream == stream


def test_stream_settings_a_run_did_not_save_take_their_defaults(tmp_path: Path) -> None:
    saved = asdict(StreamConfig(seed=3))
    del saved["repairs"], saved["local"]["samples"]
    assert read_run(_run(tmp_path, stream=saved)).stream == replace(StreamConfig(), seed=3)
    assert read_run(_run(tmp_path / "old")).stream == StreamConfig()


@pytest.mark.parametrize(
    ("stream", "message"),
    [
        (
            {"alpha_schedul": "dynamic"},
            r"stream: StreamConfig: unknown settings \['alpha_schedul'\]",
        ),
        ({"local": {"sample": 3}}, r"stream: LocalConfig: unknown settings \['sample'\]"),
        ({"alpha": 2.0}, r"stream: StreamConfig.alpha = 2.0: out of range"),
        ({"transfer": "all"}, r"stream: transfer 'all': one of"),
        ({"alpha": "high"}, r"stream: '<=' not supported"),
        ([1, 2], r"stream: not a JSON object"),
    ],
)
def test_a_bad_stream_setting_is_one_error_naming_config_json(
    tmp_path: Path, stream: object, message: str
) -> None:
    with pytest.raises(LolgpsError, match=f"corrupt .*config.json: {message}"):
        read_run(_run(tmp_path, stream=stream))


def test_metrics_read_back_without_a_torn_last_line(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path)
    folder.append_metrics({"iteration": 0})
    folder.append_metrics({"iteration": 1})
    with open(folder.metrics_path, "a") as fh:
        fh.write('{"iterat')  # a kill mid-line
    assert folder.read_metrics() == [{"iteration": 0}, {"iteration": 1}]
    folder.metrics_path.write_text('{"a": 1}\nbroken\n{"b": 2}\n')
    with pytest.raises(LolgpsError, match="line 2"):
        folder.read_metrics()


def test_a_policy_saved_before_output_scaling_loads_as_the_same_policy() -> None:
    policy = GaussianPolicy(3, 2, PolicyConfig(hidden_sizes=(8,)))
    policy.set_whitening(torch.randn(20, 3, dtype=F64))
    old = {k: v for k, v in policy.state_dict().items() if k not in ("u_mean", "u_scale")}
    loaded = GaussianPolicy.from_state(policy.description(), old)
    x = torch.randn(4, 3, dtype=F64)
    assert torch.equal(loaded(x), policy(x))
    assert torch.equal(loaded.u_scale, torch.ones(2, dtype=F64))


def test_evaluated_runs_are_a_run_or_a_sweeps_runs(tmp_path: Path) -> None:
    for name in ("b", "a", "unevaluated"):
        (tmp_path / name).mkdir()
    for name in ("a", "b"):
        (tmp_path / name / "eval.json").write_text("{}")
    assert evaluated_runs(tmp_path) == [tmp_path / "a", tmp_path / "b"]
    assert evaluated_runs(tmp_path / "a") == [tmp_path / "a"]
    with pytest.raises(LolgpsError, match="no evaluated run"):
        evaluated_runs(tmp_path / "unevaluated")
