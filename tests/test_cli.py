"""Command-line plumbing: flags derived from config dataclasses, the ``lolgps`` command and
its run's checks, all made before anything is written."""

from __future__ import annotations

import argparse
import json
import runpy
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from lolgps_torch.cli import ConfigFlags, read_offsets
from lolgps_torch.commands import lolgps
from lolgps_torch.commands import run as run_command
from lolgps_torch.commands.stream import Plan, plan_stream
from lolgps_torch.data.run_folder import RunFolder
from lolgps_torch.errors import LolgpsError

ROOT = Path(__file__).resolve().parents[1]
RUN_STREAM = ROOT / "scripts" / "run_stream.py"


@dataclass(frozen=True)
class Inner:
    """Nested settings.

    :param steps: Adam steps, 100% of them.
    """

    steps: int = 10


@dataclass(frozen=True)
class Outer:
    """Settings.

    :param rate: a step size
        over two lines.
    :param mode: how to go. :param replay: use the replay.
    :param width: optional width.
    :param pose: a pose (rad).
    :param inner: nested.
    """

    rate: float = 0.5
    mode: Literal["fast", "slow"] = "fast"
    replay: bool = True
    width: int | None = None
    pose: tuple[float, ...] | None = None
    inner: Inner = field(default_factory=Inner)


FLAGS = ConfigFlags(
    Outer(), renames={"steps": ("inner.steps",), "no-replay": ("replay",)}, skip=("width",)
)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    FLAGS.add_to(parser)
    return parser


def test_flags_follow_the_dataclass_fields() -> None:
    parser = _parser()
    actions = {a.dest: a for a in parser._actions}
    assert set(actions) == {"help", "rate", "mode", "pose", "steps", "no_replay"}
    assert actions["mode"].choices == ["fast", "slow"]
    assert actions["rate"].type is float and actions["rate"].default == 0.5
    assert actions["steps"].type is int and actions["steps"].default == 10
    assert actions["rate"].help == "a step size over two lines (default %(default)s)"
    assert actions["steps"].help == "Adam steps, 100%% of them (default %(default)s)"
    assert "(default" not in str(actions["no_replay"].help)
    assert Outer() == FLAGS.build(parser.parse_args([]))
    built = FLAGS.build(
        parser.parse_args(
            ["--rate", "2", "--mode", "slow", "--steps", "3", "--no-replay", "--pose", "1", "2"]
        )
    )
    assert built == Outer(rate=2.0, mode="slow", replay=False, pose=(1.0, 2.0), inner=Inner(3))
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "medium"])


def test_an_optional_number_takes_none() -> None:
    flags = ConfigFlags(Outer(width=3), renames={"steps": ("inner.steps",)}, skip=("replay",))
    parser = argparse.ArgumentParser()
    flags.add_to(parser)
    assert flags.build(parser.parse_args(["--width", "none"])).width is None
    assert flags.build(parser.parse_args(["--width", "7"])).width == 7
    with pytest.raises(SystemExit):
        parser.parse_args(["--width", "wide"])


def test_a_field_without_a_documented_param_is_a_programming_error() -> None:
    @dataclass(frozen=True)
    class Undocumented:
        """No params."""

        rate: float = 1.0

    with pytest.raises(TypeError, match="documents no :param rate:"):
        ConfigFlags(Undocumented()).add_to(argparse.ArgumentParser())


def test_offsets_must_be_finite_pairs(tmp_path: Path) -> None:
    path = tmp_path / "offsets.json"
    path.write_text("[[0.0, 0.01], [0.02, -0.01]]")
    assert read_offsets(str(path), "--conditions") == [(0.0, 0.01), (0.02, -0.01)]
    for text, message in [
        ("[[NaN, 0]]", "finite numbers, got \\[nan, 0.0\\]"),
        ("[[1, 2, 3]]", "expected a JSON list of \\[dx, dy\\]"),
        ("[]", "is empty"),
    ]:
        path.write_text(text)
        with pytest.raises(LolgpsError, match=message):
            read_offsets(str(path), "--conditions")


def _plan(argv: list[str]) -> Plan:
    """The plan of ``lolgps run ARGV``, written nowhere."""
    return plan_stream(run_command.stream_settings(run_command.build_parser().parse_args(argv)))


def _run_stream(
    argv: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> list[str]:
    """run_stream.py's stderr lines, the script having exited with code 2."""
    monkeypatch.setattr(sys, "argv", ["run_stream.py", *argv])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(RUN_STREAM), run_name="__main__")
    assert exit_info.value.code == 2
    return capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize(
    ("extra", "conditions", "message"),
    [
        (["--device", "banana"], "[[0, 0]]", "error: --device banana: "),
        ([], "[[NaN, 0]]", "error: --conditions "),
        (
            ["--max-iterations", "0"],
            "[[0, 0]]",
            "error: StreamConfig.max_iterations = 0: out of range",
        ),
        ([], "[[5.0, 0.0], [-5.0, 0.0]]", "error: the 2 hole positions (spread 10.00 m)"),
        (["--resume"], "[[0, 0]]", "error: --resume: "),
    ],
)
def test_run_stream_checks_everything_before_writing(
    extra: list[str],
    conditions: str,
    message: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    (tmp_path / "conditions.json").write_text(conditions)
    argv = ["--conditions", str(tmp_path / "conditions.json"), "--out", str(tmp_path / "run")]
    err = _run_stream([*argv, *extra], monkeypatch, capsys)
    assert len(err) == 1 and err[0].startswith(message), err
    assert not (tmp_path / "run").exists()


def test_run_stream_refuses_an_unwritable_out(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _run_stream(["--out", "/proc/nope"], monkeypatch, capsys)
    assert len(err) == 1 and err[0].startswith("error: cannot write to /proc/nope")
    assert not Path("/proc/nope").exists()


def test_resume_names_the_fields_that_differ(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "conditions.json").write_text("[[0, 0]]")
    argv = ["--conditions", str(tmp_path / "conditions.json"), "--out", str(tmp_path / "run")]
    plan = _plan(argv)
    RunFolder(tmp_path / "run").start(plan.config, plan.urdf_text)
    before = sorted(p.name for p in (tmp_path / "run").iterdir())
    err = _run_stream([*argv, "--resume", "--max-iterations", "3"], monkeypatch, capsys)
    assert len(err) == 1
    assert err[0] == (
        f"error: {tmp_path / 'run'} holds a run with another configuration: "
        "stream.max_iterations: 25 (saved) vs 3 (now)"
    )
    assert (
        sorted(p.name for p in (tmp_path / "run").iterdir())
        == before
        == [
            "arm.urdf",
            "config.json",
        ]
    )
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["task"]["urdf"] == "robots/kuka_peg.urdf"
    assert len(saved["task"]["urdf_sha256"]) == 64


NUMERIC_FLAGS = [
    "--alpha", "--alpha-step", "--success-phases", "--augment", "--augment-scale",
    "--max-iterations", "--samples", "--distill-steps", "--pre-weight", "--seed", "--count",
    "--friction", "--action-weight", "--descent-height", "--descent-steps", "--peg-length",
    "--peg-radius", "--model-plans",
]  # fmt: skip
VALUES = ["nan", "inf", "-inf", "-1", "0", "1e308", "2", "0.5", "x", "", "1e-300"]


def test_fuzzed_numeric_flags_are_accepted_or_refused_before_writing(tmp_path: Path) -> None:
    """Seeded random values of every numeric flag of run_stream.py: each is refused by
    argparse (exit 2) or by the configs' checks (LolgpsError), or planned, and nothing is
    written either way; never another exception."""
    (tmp_path / "conditions.json").write_text("[[0.0, 0.0]]")
    base = ["--conditions", str(tmp_path / "conditions.json"), "--out", str(tmp_path / "run")]
    rng = __import__("random").Random(0)
    outcomes = {"argparse": 0, "refused": 0, "planned": 0}
    pairs = [(flag, value) for flag in NUMERIC_FLAGS for value in VALUES]
    for flag, value in rng.sample(pairs, 12):  # 12 different pairs of the 198
        try:
            _plan([*base, flag, value])
            outcomes["planned"] += 1
        except SystemExit as error:
            assert error.code == 2
            outcomes["argparse"] += 1
        except LolgpsError:
            outcomes["refused"] += 1
        assert not (tmp_path / "run").exists(), (flag, value)
    assert all(outcomes.values()), outcomes  # each kind of outcome was exercised


def test_fuzzed_conditions_files_are_read_or_refused(tmp_path: Path) -> None:
    """Seeded random JSON for --conditions: finite [dx, dy] pairs, or one LolgpsError."""
    rng = __import__("random").Random(1)
    atoms = ["0.01", "NaN", "Infinity", "-0.02", '"a"', "null", "[]", "{}", "true", "1e400"]
    path = tmp_path / "conditions.json"
    for _ in range(200):
        pairs = [
            "[" + ", ".join(rng.choice(atoms) for _ in range(rng.randint(0, 3))) + "]"
            for _ in range(rng.randint(0, 3))
        ]
        text = "[" + ", ".join(pairs) + "]"
        path.write_text(text if rng.random() > 0.1 else text[: rng.randint(0, len(text))])
        try:
            offsets = read_offsets(str(path), "--conditions")
        except LolgpsError:
            continue
        assert offsets and all(len(o) == 2 for o in offsets)
        assert all(abs(v) < float("inf") for o in offsets for v in o), text


def _lolgps(
    argv: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> tuple[int, str, str]:
    """``lolgps ARGV`` in this process: its exit status, stdout and stderr."""
    monkeypatch.setattr(sys, "argv", ["lolgps", *argv])
    try:
        lolgps.main()
        code = 0
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def test_lolgps_names_its_commands_and_refuses_others(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = _lolgps(["--help"], monkeypatch, capsys)
    assert code == 0 and all(f"  {name} " in out for name in lolgps.COMMANDS)
    assert list(lolgps.COMMANDS) == ["run", "evaluate", "sweep", "export", "render", "report"]
    code, _, err = _lolgps([], monkeypatch, capsys)
    assert code == 2 and err.startswith("error: expected a command, one of run, ")
    code, _, err = _lolgps(["train"], monkeypatch, capsys)
    assert (
        code == 2
        and err
        == "error: unknown command 'train': choose from " + ", ".join(lolgps.COMMANDS) + "\n"
    )


SCRIPTS = {
    "run": "run_stream.py",
    "evaluate": "evaluate.py",
    "sweep": "sweep.py",
    "export": "export_dataset.py",
    "render": "render.py",
    "report": "report.py",
}


@pytest.mark.parametrize("command", sorted(SCRIPTS))
def test_each_command_takes_its_scripts_flags_and_says_them_in_its_help(
    command: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``lolgps COMMAND --help`` is ``scripts/SCRIPT --help`` but for the name in the usage,
    and holds the user documentation (the usage lines)."""
    prog, script = f"lolgps {command}", SCRIPTS[command]
    code, ours, _ = _lolgps([command, "--help"], monkeypatch, capsys)
    monkeypatch.setattr(sys, "argv", [script, "--help"])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(ROOT / "scripts" / script), run_name="__main__")
    theirs = capsys.readouterr().out
    assert code == exit_info.value.code == 0
    (our_usage, our_text), (their_usage, their_text) = (h.split("\n\n", 1) for h in (ours, theirs))
    assert our_usage.replace(prog, "").split() == their_usage.replace(script, "").split()
    assert our_text == their_text
    assert f"    {prog} --" in ours and f"python scripts/{script}" in ours


def test_lolgps_run_refuses_bad_input_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "conditions.json").write_text("[[0, 0]]")
    argv = ["run", "--conditions", str(tmp_path / "conditions.json"), "--out", str(tmp_path)]
    code, _, err = _lolgps([*argv, "--device", "banana"], monkeypatch, capsys)
    assert code == 2 and err.startswith("error: --device banana: ") and err.count("\n") == 1
