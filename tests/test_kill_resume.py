"""Nothing lost to a kill or a damaged file: a CI-sized stream SIGKILLed at moments read from
what the run writes (an iteration record, an S-step, the replay's temporary file), then
resumed, ends with the uninterrupted run's summary and policy; a truncated replay,
checkpoint or config.json met by ``--resume``, ``evaluate.py`` or ``export_dataset.py`` is one
``error:`` line naming the file, exit status 2."""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
import torch
from conftest import ScriptRun, ci_stream_command, finish_script, start_script

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.data.checkpoint import load_policy

Moment = Callable[[Path], bool]
_command = ci_stream_command


def _records(out: Path) -> list[dict[str, Any]]:
    """metrics.jsonl so far; a line being written is left out."""
    try:
        lines = (out / "metrics.jsonl").read_text().splitlines()
    except FileNotFoundError:
        return []
    records = []
    for line in lines:
        try:
            records.append(json.loads(line))
        except ValueError:
            break
    return records


def _distilled(records: list[dict[str, Any]], condition: int) -> bool:
    return any(r.get("event") == "distilled" and r["condition"] == condition for r in records)


@pytest.fixture(scope="module")
def reference(ci_stream: Path) -> Path:
    """An uninterrupted run of the CI-sized stream."""
    return ci_stream / "run"


def _kill_at(command: list[str], out: Path, moment: Moment, poll: float) -> None:
    """Start the stream and SIGKILL it as soon as ``moment(out)`` holds, polled every
    ``poll`` seconds; fail if the run ends first."""
    log = out.parent / "stream.log"
    process = start_script(command, log)
    deadline = time.monotonic() + 900
    while not moment(out):
        if not process.is_alive() or time.monotonic() > deadline:
            process.kill()
            process.join()
            pytest.fail(f"the run ended before the moment to kill it: {log.read_text()[-2000:]}")
        time.sleep(poll)
    assert process.pid is not None
    os.kill(process.pid, signal.SIGKILL)
    process.join()
    assert process.exitcode == -signal.SIGKILL


def _iteration_logged(condition: int, iteration: int) -> Moment:
    return lambda out: any(
        r.get("condition") == condition and r.get("iteration") == iteration and "event" not in r
        for r in _records(out)
    )


def _replay_partial(out: Path) -> bool:
    return (out / "replay.h5.partial").exists()


def _group_bytes(path: Path, group: str) -> dict[str, bytes]:
    with h5py.File(path, "r") as f:
        return {name: np.asarray(ds).tobytes() for name, ds in f[group].items()}


@pytest.mark.slow  # three kills and resumes; the default suite kills once (below)
def test_killed_three_times_the_resumed_run_ends_as_the_uninterrupted_one(
    reference: Path, tmp_path: Path
) -> None:
    """One run killed (a) right after its first iteration record, before any condition was
    complete; (b) during the last condition's S-step, after its last iteration record and
    before its "distilled" record; (c) while the replay is being appended, as soon as
    ``replay.h5.partial`` appears (the append takes 0.1-0.3 s; polled every ms). After each
    kill the files already complete read back unchanged; resumed, it ends with the
    uninterrupted run's summary.json, replay and final policy."""
    out = tmp_path / "run"
    command = _command(tmp_path, out)
    replay = out / "replay.h5"

    _kill_at(command, out, _iteration_logged(0, 0), poll=0.005)  # (a)
    assert not replay.exists() and not (out / "checkpoints").exists()

    expected = _records(reference)
    end = next(i for i, r in enumerate(expected) if _distilled([r], 1))
    last_iteration = expected[end - 1]  # the last condition's last iteration record
    assert last_iteration.get("condition") == 1 and "iteration" in last_iteration
    in_s_step = _iteration_logged(1, last_iteration["iteration"])
    _kill_at([*command, "--resume"], out, in_s_step, poll=0.005)  # (b)
    assert not _distilled(_records(out), 1), "killed after the S-step, not during it"
    assert ReplayBuffer(replay).conditions() == [0]
    first = _group_bytes(replay, "condition_000")
    assert load_policy(out / "checkpoints" / "after_condition_000").trained

    _kill_at([*command, "--resume"], out, _replay_partial, poll=0.001)  # (c)
    assert (out / "replay.h5.partial").exists(), "killed after the append, not during it"
    assert ReplayBuffer(replay).conditions() == [0]
    assert _group_bytes(replay, "condition_000") == first

    _resumed_to_the_end(command, out, reference)


def test_killed_while_writing_the_replay_the_resumed_run_ends_as_the_uninterrupted_one(
    reference: Path, tmp_path: Path
) -> None:
    """The default suite's kill: the run SIGKILLed while the first condition's replay group
    is being appended (moment (c) above, before any condition was complete), then resumed,
    ends with the uninterrupted run's summary.json, replay and final policy."""
    out = tmp_path / "run"
    command = _command(tmp_path, out)
    _kill_at(command, out, _replay_partial, poll=0.001)
    assert (out / "replay.h5.partial").exists(), "killed after the append, not during it"
    assert not (out / "replay.h5").exists()
    _resumed_to_the_end(command, out, reference)


def _resumed_to_the_end(command: list[str], out: Path, reference: Path) -> None:
    """Resume the run in ``out`` to its end; it must end with ``reference``'s summary.json,
    replay groups and final policy, and no partial replay."""
    log = out.parent / "stream.log"
    code = finish_script(start_script([*command, "--resume"], log), log)
    assert code == 0, log.read_text()[-2000:]
    assert not (out / "replay.h5.partial").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary == json.loads((reference / "summary.json").read_text())
    for group in ("condition_000", "condition_001"):
        assert _group_bytes(out / "replay.h5", group) == _group_bytes(
            reference / "replay.h5", group
        )
    final = out / "checkpoints" / "after_condition_001"
    ours, theirs = (
        load_policy(p).state_dict() for p in (final, reference / final.relative_to(out))
    )
    assert ours.keys() == theirs.keys()
    assert all(torch.equal(ours[key], theirs[key]) for key in ours)


# -- damaged files ---------------------------------------------------------------------------


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


POLICY = "checkpoints/after_condition_001/policy.pt"
DESCRIPTION = "checkpoints/after_condition_001/policy.json"
CASES = [
    ("run_stream.py", "replay.h5"),
    ("run_stream.py", POLICY),  # policy.json: the same load_policy as evaluate.py's below
    ("run_stream.py", "config.json"),
    ("evaluate.py", POLICY),
    ("evaluate.py", DESCRIPTION),
    ("evaluate.py", "config.json"),
    ("export_dataset.py", "replay.h5"),
    ("export_dataset.py", "config.json"),
]


@pytest.mark.parametrize(("script", "damaged"), CASES)
def test_a_truncated_file_is_one_error_naming_it(
    script: str,
    damaged: str,
    reference: Path,
    tmp_path: Path,
    run_script: Callable[..., ScriptRun],
) -> None:
    run = tmp_path / "run"
    shutil.copytree(reference, run)
    _truncate(run / damaged)
    args = {
        "run_stream.py": _command(tmp_path, run)[2:] + ["--resume"],
        "evaluate.py": ["--run", str(run), "--positions", str(tmp_path / "positions.json")],
        "export_dataset.py": ["--run", str(run), "--out", str(tmp_path / "export.h5")],
    }[script]
    (tmp_path / "positions.json").write_text("[[0.0, 0.0]]")
    result = run_script(
        f"scripts/{script}", *args, *(["--workers", "1"] if script == "evaluate.py" else [])
    )
    assert result.code == 2
    lines = result.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.err
    assert str(run / damaged) in lines[0]
    assert not (tmp_path / "export.h5").exists() and not (run / "eval.json").exists()
