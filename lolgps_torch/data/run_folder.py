"""The run folder: one place that knows where a run keeps what, and writes it atomically.

    <run>/config.json                          the resolved configuration (written once)
    <run>/arm.urdf                             the arm's URDF, mesh paths made absolute
    <run>/metrics.jsonl                        one record per iteration and per S-step
    <run>/replay.h5                            D_g of every finished condition
    <run>/checkpoints/after_condition_XXX/     the global policy after condition XXX,
                                               with entry.json (its summary entry)
    <run>/summary.json                         every condition's entry, written at the end
    <run>/eval.json, fig4.png                  the evaluation's results

A condition is complete once its replay group exists; its checkpoint and entry are written
before it (see :class:`lolgps_torch.lolgps.stream.StreamLearner`).

A run folder stands alone: everything that loads a run builds its task from ``arm.urdf``
(checked against ``task.urdf_sha256`` in config.json), not from the path the user gave,
which config.json keeps for display.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from lolgps_torch.errors import LolgpsError
from lolgps_torch.robot.arm import declare_prefixes
from lolgps_torch.robot.packages import resolve_mesh
from lolgps_torch.task import TaskConfig, task_config_from_dict

CONFIG_FILE = "config.json"
URDF_FILE = "arm.urdf"
SUMMARY_FILE = "summary.json"
METRICS_FILE = "metrics.jsonl"
REPLAY_FILE = "replay.h5"
EVAL_FILE = "eval.json"
FIGURE_FILE = "fig4.png"
CHECKPOINT_DIR = "checkpoints"
ENTRY_FILE = "entry.json"


def fsync_path(path: Path) -> None:
    """Flush ``path`` (a file or a directory) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_error(path: str | Path, error: OSError) -> LolgpsError:
    """The :class:`LolgpsError` for ``error`` while writing ``path``: "disk full while
    writing <path>" for ENOSPC (and EDQUOT), "cannot write <path>" otherwise."""
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return LolgpsError(f"disk full while writing {path}: {os.strerror(error.errno)}")
    text = str(error.strerror or error).strip()
    return LolgpsError(f"cannot write {path}: {text.splitlines()[0] if text else 'OSError'}")


def atomic_write(path: str | Path, write: Callable[[Path], object]) -> None:
    """Write ``path`` through a temporary sibling, fsync it and ``os.replace`` it into place,
    so a reader (or a resumed run) never sees a partial file. ``write`` gets the temporary
    path. The project's only way of replacing a file it has written before. An OSError (a
    full disk) is a :class:`LolgpsError` naming ``path``; the temporary file is removed and
    the previous ``path`` kept."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except OSError as error:
        raise write_error(path, error) from error
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: str | Path, data: Any) -> None:
    """``data`` as indented JSON at ``path``, atomically."""
    text = json.dumps(data, indent=1) + "\n"
    atomic_write(path, lambda tmp: tmp.write_text(text))


def read_json(path: str | Path) -> Any:
    """The JSON at ``path``; a missing, unreadable or corrupt file is a :class:`LolgpsError`
    that names it."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except OSError as error:
        raise LolgpsError(f"cannot read {path}: {error.strerror or error}") from None
    except ValueError as error:
        raise LolgpsError(f"corrupt {path}: {error}") from None


def portable_urdf(path: str, package_path: Sequence[str] = ()) -> str:
    """The URDF at ``path`` as text that reads the same from any folder: every mesh filename
    that resolves (:func:`~lolgps_torch.robot.packages.resolve_mesh`) made absolute;
    without such meshes, the file's text unchanged. PyBullet and yourdfpy accept absolute
    filenames. Undeclared namespace prefixes are declared first
    (:func:`~lolgps_torch.robot.arm.declare_prefixes`)."""
    try:
        text = Path(path).read_text()
        tree = ET.fromstring(declare_prefixes(text))
    except OSError as error:
        raise LolgpsError(f"cannot read URDF {path}: {error.strerror or error}") from None
    except ET.ParseError as error:
        raise LolgpsError(f"{path}: malformed XML ({error})") from None
    changed = False
    for mesh in tree.iter("mesh"):
        resolved = resolve_mesh(mesh.get("filename", ""), path, package_path)
        if resolved is not None and resolved != mesh.get("filename"):
            mesh.set("filename", os.path.abspath(resolved))
            changed = True
    return ET.tostring(tree, encoding="unicode") if changed else text


def arm_urdf(task: TaskConfig) -> str:
    """The run folder's copy of ``task``'s arm: its URDF made portable (:func:`portable_urdf`),
    or the URDF an MJCF arm reads as (:func:`~lolgps_torch.robot.mjcf.mjcf_urdf`)."""
    if task.mjcf:
        from lolgps_torch.robot.mjcf import mjcf_urdf  # imports MuJoCo, an extra

        return mjcf_urdf(task.urdf)
    return portable_urdf(task.urdf, task.package_path)


def as_stored(data: Any) -> Any:
    """``data`` as it reads back from JSON (tuples become lists), for comparing with a file."""
    return json.loads(json.dumps(data))


def task_json(task: TaskConfig, urdf_text: str) -> dict[str, Any]:
    """``task`` as config.json stores it: its fields (the user's URDF path for display) and
    ``urdf_sha256``, the SHA-256 of the run folder's copy ``urdf_text``."""
    digest = hashlib.sha256(urdf_text.encode()).hexdigest()
    stored: dict[str, Any] = as_stored({**asdict(task), "urdf_sha256": digest})
    return stored


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """The leaves of nested dicts, keyed by their dotted paths (``{"a": {"b": 1}}`` ->
    ``{"a.b": 1}``)."""
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in data.items():
        out.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def config_differences(saved: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """``"key.path: saved (saved) vs now (now)"`` for every leaf where two configurations
    differ (a key missing on one side shows as None)."""
    old, new = flatten(saved), flatten(now)
    return [
        f"{key}: {old.get(key)} (saved) vs {new.get(key)} (now)"
        for key in sorted(old.keys() | new.keys())
        if old.get(key) != new.get(key)
    ]


class RunFolder:
    """Paths and JSON I/O of one run folder (layout in the module docstring).

    :param path: the folder; nothing is created until something is written.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    @property
    def config_path(self) -> Path:
        return self.path / CONFIG_FILE

    @property
    def summary_path(self) -> Path:
        return self.path / SUMMARY_FILE

    @property
    def metrics_path(self) -> Path:
        return self.path / METRICS_FILE

    @property
    def replay_path(self) -> Path:
        return self.path / REPLAY_FILE

    @property
    def eval_path(self) -> Path:
        return self.path / EVAL_FILE

    @property
    def figure_path(self) -> Path:
        return self.path / FIGURE_FILE

    def checkpoint_dir(self, condition: int) -> Path:
        """The folder of the global policy saved after ``condition``."""
        return self.path / CHECKPOINT_DIR / f"after_condition_{condition:03d}"

    def entry_path(self, condition: int) -> Path:
        return self.checkpoint_dir(condition) / ENTRY_FILE

    @property
    def urdf_path(self) -> Path:
        return self.path / URDF_FILE

    def check_writable(self) -> None:
        """Raise :class:`LolgpsError` unless a run can be written here: probe the folder (or
        its nearest existing parent) with a temporary folder, removed again, so a failed check
        leaves nothing behind."""
        probe = self.path
        while not probe.exists():
            probe = probe.parent
        if not probe.is_dir():
            raise LolgpsError(f"cannot create {self.path}: {probe} is not a folder")
        try:
            os.rmdir(tempfile.mkdtemp(prefix=".probe-", dir=probe))
        except OSError as error:
            raise LolgpsError(f"cannot write to {self.path}: {error.strerror or error}") from None

    def start(self, config: dict[str, Any], urdf_text: str) -> None:
        """Create the run: the arm's URDF copy, then config.json (which marks the run as
        existing, so it is written last)."""
        self.path.mkdir(parents=True, exist_ok=True)
        atomic_write(self.urdf_path, lambda tmp: tmp.write_text(urdf_text))
        self.write_config(config)

    def task_config(self, task: dict[str, Any]) -> TaskConfig:
        """The :class:`TaskConfig` of ``task`` (config.json's ``task``) with the URDF read from
        this folder's copy, checked against ``urdf_sha256``; runs without a copy keep the
        recorded path."""
        config = task_config_from_dict(task)
        if not self.urdf_path.is_file():
            return config
        digest = hashlib.sha256(self.urdf_path.read_bytes()).hexdigest()
        if digest != task.get("urdf_sha256"):
            raise LolgpsError(f"{self.urdf_path} does not match its SHA-256 in config.json")
        return replace(config, urdf=str(self.urdf_path.resolve()), mjcf=False)

    def has_config(self) -> bool:
        return self.config_path.is_file()

    def read_config(self) -> dict[str, Any]:
        config = read_json(self.config_path)
        if not isinstance(config, dict):
            raise LolgpsError(f"corrupt {self.config_path}: not a JSON object")
        return config

    def write_config(self, config: dict[str, Any]) -> None:
        write_json(self.config_path, config)

    def read_summary(self) -> dict[str, Any]:
        summary = read_json(self.summary_path)
        if not isinstance(summary, dict) or not isinstance(summary.get("conditions"), list):
            raise LolgpsError(f"corrupt {self.summary_path}: no list of conditions")
        return summary

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_json(self.summary_path, summary)

    def read_entry(self, condition: int) -> dict[str, Any]:
        entry = read_json(self.entry_path(condition))
        if not isinstance(entry, dict):
            raise LolgpsError(f"corrupt {self.entry_path(condition)}: not a JSON object")
        return entry

    def write_entry(self, condition: int, entry: dict[str, Any]) -> None:
        write_json(self.entry_path(condition), entry)

    def read_metrics(self) -> list[dict[str, Any]]:
        """Every line of ``metrics.jsonl`` (a torn last line, from a kill, is left out)."""
        try:
            lines = self.metrics_path.read_text().splitlines()
        except OSError as error:
            raise LolgpsError(f"cannot read {self.metrics_path}: {error.strerror}") from None
        records = []
        for number, line in enumerate(lines):
            try:
                records.append(json.loads(line))
            except ValueError:
                if number < len(lines) - 1:
                    raise LolgpsError(f"corrupt {self.metrics_path}: line {number + 1}") from None
        return records

    def append_metrics(self, record: dict[str, Any]) -> None:
        """One line of ``metrics.jsonl`` (appended and flushed; a torn last line is harmless,
        nothing reads the metrics back to resume)."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            with open(self.metrics_path, "a") as fh:
                fh.write(json.dumps(record) + "\n")
        except OSError as error:
            raise write_error(self.metrics_path, error) from error


def runs_holding(folder: str | Path, name: str, what: str) -> list[Path]:
    """``folder`` if it holds the file ``name``, else its subfolders that do (a sweep's); none
    is a :class:`LolgpsError` naming ``what`` was looked for."""
    folder = Path(folder)
    if (folder / name).is_file():
        return [folder]
    found = sorted(p.parent for p in folder.glob(f"*/{name}"))
    if not found:
        raise LolgpsError(f"{folder}: no {what} ({name}) in it")
    return found


def evaluated_runs(folder: str | Path) -> list[Path]:
    """``folder`` if it is an evaluated run (it holds an ``eval.json``), else its evaluated
    run subfolders (a sweep's); none is a :class:`LolgpsError`."""
    return runs_holding(folder, EVAL_FILE, "evaluated run")
