"""The run folder: one place that knows where a run keeps what, and writes it atomically.

    <run>/config.json                          the resolved configuration (written once)
    <run>/metrics.jsonl                        one record per iteration and per S-step
    <run>/replay.h5                            D_g of every finished condition
    <run>/checkpoints/after_condition_XXX/     the global policy after condition XXX,
                                               with entry.json (its summary entry)
    <run>/summary.json                         every condition's entry, written at the end
    <run>/eval.json, fig4.png                  the evaluation's results

A condition is complete once its replay group exists; its checkpoint and entry are written
before it (see :class:`lolgps_torch.lolgps.stream.StreamLearner`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lolgps_torch.errors import LolgpsError

CONFIG_FILE = "config.json"
SUMMARY_FILE = "summary.json"
METRICS_FILE = "metrics.jsonl"
REPLAY_FILE = "replay.h5"
EVAL_FILE = "eval.json"
CHECKPOINT_DIR = "checkpoints"
ENTRY_FILE = "entry.json"


def fsync_path(path: Path) -> None:
    """Flush ``path`` (a file or a directory) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: str | Path, write: Callable[[Path], object]) -> None:
    """Write ``path`` through a temporary sibling, fsync it and ``os.replace`` it into place,
    so a reader (or a resumed run) never sees a partial file. ``write`` gets the temporary
    path. The project's only way of replacing a file it has written before."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    try:
        write(tmp)
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
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

    def checkpoint_dir(self, condition: int) -> Path:
        """The folder of the global policy saved after ``condition``."""
        return self.path / CHECKPOINT_DIR / f"after_condition_{condition:03d}"

    def entry_path(self, condition: int) -> Path:
        return self.checkpoint_dir(condition) / ENTRY_FILE

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

    def append_metrics(self, record: dict[str, Any]) -> None:
        """One line of ``metrics.jsonl`` (appended and flushed; a torn last line is harmless,
        nothing reads the metrics back to resume)."""
        self.path.mkdir(parents=True, exist_ok=True)
        with open(self.metrics_path, "a") as fh:
            fh.write(json.dumps(record) + "\n")
