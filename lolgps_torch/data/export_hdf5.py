"""Export a run folder as one self-describing HDF5 dataset, and load it back as torch tensors.
The schema is documented in ``datasets/README.md``.

The export writes under a temporary name next to the output and renames it into place when
complete, so an interrupted export never leaves anything at the output path. One writer per
output: a stale temporary from a crash is replaced by the next export.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

import lolgps_torch
from lolgps_torch.data.dataset import (
    CONDITIONS,
    FORMAT,
    READABLE_SCHEMA_VERSIONS,
    ExportedTrajectories,
    ExportReport,
    RunData,
    check_output,
    one_line,
    read_run,
)
from lolgps_torch.data.run_folder import atomic_write
from lolgps_torch.errors import LolgpsError
from lolgps_torch.progress import progress

TRAJECTORIES = "trajectories"
VISITED = "visited"
# Groups whose attributes hold the metadata (the root's are written separately).
META_GROUPS = ("arm", "state", "task", "cost")
# Root attributes stored as JSON text.
JSON_ATTRS = ("run_config", "run_summary")


def _to_attr(key: str, value: Any) -> Any:
    """A metadata value as an HDF5 attribute: JSON text for ``JSON_ATTRS``, lists as arrays."""
    if key in JSON_ATTRS:
        return json.dumps(value)
    if isinstance(value, list):
        array = np.asarray(value)
        return array.astype(h5py.string_dtype()) if array.dtype.kind == "U" else array
    return value


def _from_attr(key: str, value: Any) -> Any:
    """Inverse of :func:`_to_attr` to plain Python values."""
    if key in JSON_ATTRS:
        return json.loads(value)
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value


def _write_attrs(obj: h5py.Group, values: dict[str, Any]) -> None:
    for key, value in values.items():
        if value is not None:
            obj.attrs[key] = _to_attr(key, value)


def _write_dataset(group: h5py.Group, name: str, array: np.ndarray) -> None:
    """Chunked per trajectory (first axis), shuffled, gzip-compressed and checksummed."""
    group.create_dataset(
        name,
        data=array,
        chunks=(1, *array.shape[1:]) if array.ndim > 1 else True,
        maxshape=(None, *array.shape[1:]),
        compression="gzip",
        shuffle=True,
        fletcher32=True,
    )


def _write_hdf5(tmp: Path, run: RunData) -> None:
    with h5py.File(tmp, "w", libver="v110") as f:
        _write_attrs(f, run.root)
        for name in META_GROUPS:
            _write_attrs(f.create_group(name), run.meta[name])
        table = f.create_group(CONDITIONS)
        for name, array in run.conditions.items():
            _write_dataset(table, name, array)
        group = f.create_group(TRAJECTORIES)
        fields = run.trajectories._asdict()
        for name in progress(fields, len(fields), "writing"):
            _write_dataset(group, name, fields[name].numpy())
        if run.visited:
            visited = f.create_group(VISITED)
            for name, array in run.visited.items():
                visited.create_dataset(
                    name, data=array, chunks=True, compression="gzip", shuffle=True, fletcher32=True
                )


def export_hdf5(run_dir: str | Path, out_path: str | Path, force: bool = False) -> ExportReport:
    """Write the run's trajectories and metadata to one HDF5 file (schema in datasets/README.md).

    :param run_dir: a run folder made by ``scripts/run_stream.py``.
    :param out_path: the HDF5 file to write.
    :param force: overwrite an existing ``out_path``.
    :returns: what was written (steps: the T actions of every trajectory).
    """
    start = time.perf_counter()
    out = Path(out_path)
    check_output(out, force)
    run = read_run(run_dir)
    try:
        atomic_write(out, lambda tmp: _write_hdf5(tmp, run))
    except OSError as error:
        raise LolgpsError(f"cannot write {out}: {one_line(error)}") from error
    N, T = run.trajectories.cost.shape
    return ExportReport(out, N, N * T, out.stat().st_size, time.perf_counter() - start)


@contextmanager
def _open_dataset(path: Path) -> Iterator[h5py.File]:
    """Open an exported dataset and check its format and schema version; HDF5 failures (a
    truncated or corrupt file, a missing object) -> LolgpsError."""
    if not path.is_file():
        raise LolgpsError(f"dataset {path} not found")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise LolgpsError(f"{path} is not a lolgps_torch dataset")
            version = f.attrs.get("schema_version")
            if version not in READABLE_SCHEMA_VERSIONS:
                raise LolgpsError(
                    f"{path} has schema version {version}; this lolgps_torch "
                    f"({lolgps_torch.__version__}) reads schema versions "
                    f"{', '.join(str(v) for v in READABLE_SCHEMA_VERSIONS)}"
                )
            yield f
    except (OSError, KeyError, ValueError) as error:
        raise LolgpsError(f"cannot read dataset {path}: {one_line(error)}") from error


def _read_metadata(f: h5py.File) -> dict[str, Any]:
    meta: dict[str, Any] = {k: _from_attr(k, v) for k, v in f.attrs.items()}
    meta.setdefault("run_summary", None)
    for name in META_GROUPS:
        meta[name] = {k: _from_attr(k, v) for k, v in f[name].attrs.items()}
    table = {k: ds[()] for k, ds in f[CONDITIONS].items()}
    meta[CONDITIONS] = [
        {k: table[k][i].tolist() for k in table} for i in range(len(table["index"]))
    ]
    return meta


def _select_rows(
    f: h5py.File, conditions: list[int] | None, success_only: bool, path: Path
) -> np.ndarray:
    """Indices of the trajectories of the given conditions (and successful, if asked)."""
    group = f[TRAJECTORIES]
    keep = np.ones(group["condition"].shape[0], dtype=bool)
    if conditions is not None:
        stored = f[CONDITIONS]["index"][()]
        missing = sorted(set(conditions) - set(stored.tolist()))
        if missing:
            raise LolgpsError(
                f"dataset {path} holds no condition {missing[0]} "
                f"(it holds {', '.join(str(c) for c in stored)})"
            )
        keep &= np.isin(group["condition"][()], conditions)
    if success_only:
        keep &= group["success"][()]
    return np.flatnonzero(keep)


def load_dataset(
    path: str | Path,
    conditions: list[int] | None = None,
    success_only: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[ExportedTrajectories, dict[str, Any]]:
    """Load an HDF5 dataset written by :func:`export_hdf5` (schema version 2, or 1).

    :param path: the dataset file.
    :param conditions: keep only the trajectories of these condition indices (default: all).
    :param success_only: keep only successful trajectories.
    :param device: torch device of the returned tensors.
    :returns: the trajectories (stored order; ``states`` has T+1 steps in version 2 files and
        T in version 1 files, see ``meta["schema_version"]``) and the metadata: the root
        attributes (``run_config`` and ``run_summary`` parsed from JSON), one dict per
        metadata group (``arm``, ``state``, ``task``, ``cost``) and ``conditions`` (one dict
        per condition).
    """
    file = Path(path)
    with _open_dataset(file) as f:
        rows = _select_rows(f, conditions, success_only, file)
        group = f[TRAJECTORIES]
        complete = len(rows) == group["condition"].shape[0]
        tensors = {
            name: torch.from_numpy(group[name][()] if complete else group[name][rows]).to(device)
            for name in ExportedTrajectories._fields
        }
        return ExportedTrajectories(**tensors), _read_metadata(f)
