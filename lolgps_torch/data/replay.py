"""HDF5 replay of the successful trajectories ``D_g`` of each condition, with their distillation
targets (docs/ALGORITHM.md section 7), so later S-steps remember earlier conditions.

File layout: root attributes ``format`` and ``version``; one group per condition,
``condition_000``, ``condition_001``, ..., each holding (M samples, T steps)
    ``x [M, T, dX]``, ``u [M, T, dU]``, ``cost [M, T]``, ``final_distance [M]``,
    ``mean_cur [M, T, dU]``, ``prec_cur [M, T, dU, dU]``, ``mean_pre [M, T, dU]``,
    ``prec_pre [M, T, dU, dU]`` (float64, zeros where absent), ``has_pre [M]`` (bool),
    ``final_state [M, dX]`` (the state after the last action; absent from older files),
and attributes ``condition`` (index), ``offset`` (hole offset dx, dy in m), ``iterations``.
The condition's final controllers, which label states the S-step visits later (policy
corrections), are stored with it when given: ``cur_K [T, dU, dX]``, ``cur_k [T, dU]``,
``cur_cov [T, dU, dU]`` for p_cur and ``pre_K``, ``pre_k``, ``pre_cov`` for p_pre.
The states the global policy visited during the condition's S-step, labelled by the
controllers of the condition each was visited at (docs/ALGORITHM.md section 7), are stored
with it when there are any (R rows): ``visited_x [R, dX]``, ``visited_mean_cur [R, dU]``,
``visited_prec_cur [R, dU, dU]``, ``visited_mean_pre [R, dU]``, ``visited_prec_pre [R, dU, dU]``,
``visited_has_pre [R]`` (bool), ``visited_condition [R]`` and ``visited_t [R]`` (int64).
Datasets are chunked per sample, gzip-compressed and fletcher32-checksummed, in the HDF5 1.10
file format (whose metadata is checksummed too), so damage is reported on read rather than
returned as data. A group is written once and never changed.

Layout of the tensors: sample-first ``[M, T, ...]``; numpy appears only at the file boundary.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import h5py
import numpy as np
import torch

from lolgps_torch.data.run_folder import atomic_write
from lolgps_torch.errors import LolgpsError
from lolgps_torch.types import ConditionSamples, DistillBatch, LinearGaussian, VisitedRows

FORMAT = "lolgps_torch.replay"
VERSION = 1
GROUP_PREFIX = "condition_"


class ConditionRecord(NamedTuple):
    """One stored condition: its index ``condition``, hole offset ``(dx, dy)`` (m), the number
    of iterations it took, and its samples."""

    condition: int
    offset: tuple[float, float]
    iterations: int
    samples: ConditionSamples
    p_cur: LinearGaussian | None = None
    p_pre: LinearGaussian | None = None
    visited: VisitedRows | None = None


VISITED = "visited_"


def _visited_arrays(visited: VisitedRows | None) -> dict[str, np.ndarray]:
    """``visited_<field>`` arrays of the rows (none for no rows)."""
    if visited is None or visited.R == 0:
        return {}
    fields = {**visited.rows._asdict(), "condition": visited.condition, "t": visited.t}
    out = {}
    for name, tensor in fields.items():
        kind = {"has_pre": torch.bool, "condition": torch.int64, "t": torch.int64}
        out[VISITED + name] = tensor.detach().cpu().to(kind.get(name, torch.float64)).numpy()
    return out


def _read_visited(group: h5py.Group, device: torch.device | str) -> VisitedRows | None:
    """The visited rows stored in ``group``, if any."""
    if VISITED + "x" not in group:
        return None

    def read(name: str) -> torch.Tensor:
        return torch.from_numpy(group[VISITED + name][()]).to(device)

    rows = DistillBatch(*(read(name) for name in DistillBatch._fields))
    return VisitedRows(rows, read("condition"), read("t"))


def _chunks(key: str, array: np.ndarray) -> tuple[int, ...] | bool:
    """One chunk per sample for a sample's arrays; h5py's choice for the visited rows, of
    which there are thousands."""
    return (1, *array.shape[1:]) if array.ndim > 1 and not key.startswith(VISITED) else True


def _group_name(index: int) -> str:
    return f"{GROUP_PREFIX}{index:03d}"


def _expected_shapes(samples: ConditionSamples) -> dict[str, tuple[int, ...]]:
    M, T, dX = samples.x.shape
    dU = samples.u.shape[-1]
    return {
        "x": (M, T, dX),
        "u": (M, T, dU),
        "cost": (M, T),
        "final_distance": (M,),
        "mean_cur": (M, T, dU),
        "prec_cur": (M, T, dU, dU),
        "mean_pre": (M, T, dU),
        "prec_pre": (M, T, dU, dU),
        "has_pre": (M,),
        **({} if samples.final_state is None else {"final_state": (M, dX)}),
    }


def _to_numpy(samples: ConditionSamples) -> dict[str, np.ndarray]:
    """Validate shapes and convert to float64 (``has_pre`` bool) numpy arrays."""
    if samples.x.ndim != 3 or samples.u.ndim != 3:
        raise LolgpsError(
            f"replay samples need x [M, T, dX] and u [M, T, dU], got "
            f"{tuple(samples.x.shape)} and {tuple(samples.u.shape)}"
        )
    arrays: dict[str, np.ndarray] = {}
    for name, want in _expected_shapes(samples).items():
        tensor = getattr(samples, name).detach().cpu()
        if tuple(tensor.shape) != want:
            raise LolgpsError(
                f"replay samples: {name} has shape {tuple(tensor.shape)}, expected {want}"
            )
        dtype = torch.bool if name == "has_pre" else torch.float64
        arrays[name] = tensor.to(dtype).numpy()
    return arrays


def _stored_conditions(f: h5py.File) -> list[int]:
    # Indexing by name (not f.values(), which yields None for an unreadable object) makes a
    # damaged group raise.
    return sorted(int(f[name].attrs["condition"]) for name in f)


def _read_controller(
    group: h5py.Group, prefix: str, device: torch.device | str
) -> LinearGaussian | None:
    """The controller stored as ``<prefix>_K``, ``<prefix>_k``, ``<prefix>_cov``, if any."""
    if f"{prefix}_K" not in group:
        return None
    return LinearGaussian(
        *(torch.from_numpy(group[f"{prefix}_{key}"][()]).to(device) for key in ("K", "k", "cov"))
    )


def _one_line(error: BaseException) -> str:
    text = str(error.args[0] if error.args else error).strip()
    return text.splitlines()[0] if text else type(error).__name__


class ReplayBuffer:
    """The replay ``D_g`` of all conditions so far, in one HDF5 file at ``path``.

    Appending is atomic (:func:`atomic_write`): the current file is copied to
    ``<name>.partial`` in the same folder, the new group is written there, and the copy is
    fsynced and ``os.replace``-d onto ``path``. A crash at any point (even SIGKILL) leaves the previous file untouched; earlier
    groups are copied byte for byte. One writer per file: a stale ``.partial`` from a crash is
    overwritten by the next append. A failed write (a full disk) is a :class:`LolgpsError`
    naming the file; the ``.partial`` copy is removed.

    :param path: the HDF5 file (need not exist yet: an absent file is an empty replay).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    @contextmanager
    def _open(self) -> Iterator[h5py.File]:
        """Open for reading; an HDF5 failure (corrupt or truncated file) -> LolgpsError. h5py
        raises OSError for file and data errors, KeyError for unreadable objects."""
        try:
            with h5py.File(self.path, "r") as f:
                if f.attrs.get("format") != FORMAT:
                    raise LolgpsError(f"{self.path} is not a lolgps_torch replay file")
                yield f
        except (OSError, KeyError) as error:
            raise LolgpsError(f"cannot read replay {self.path}: {_one_line(error)}") from error

    def conditions(self) -> list[int]:
        """Stored condition indices, ascending (empty if the file does not exist)."""
        if not self.path.exists():
            return []
        with self._open() as f:
            return _stored_conditions(f)

    def offsets(self) -> list[tuple[float, float]]:
        """The stored conditions' hole offsets ``(dx, dy)`` (m), in condition order."""
        if not self.path.exists():
            return []
        with self._open() as f:
            return [
                (float(dx), float(dy))
                for dx, dy in (f[_group_name(i)].attrs["offset"] for i in _stored_conditions(f))
            ]

    def append_condition(
        self,
        index: int,
        offset: tuple[float, float],
        samples: ConditionSamples,
        iterations: int,
        p_cur: LinearGaussian | None = None,
        p_pre: LinearGaussian | None = None,
        visited: VisitedRows | None = None,
    ) -> None:
        """Add condition ``index`` as a new group, atomically; refuses to overwrite one.

        :param index: condition index (>= 0).
        :param offset: hole offset ``(dx, dy)`` of the condition (m).
        :param samples: its successful samples and their targets.
        :param iterations: inner-loop iterations the condition used.
        :param p_cur: the condition's final local controller (stored when given).
        :param p_pre: its final linearised global policy (stored when given).
        :param visited: the labelled states the policy visited in its S-step (stored when any).
        """
        if index < 0:
            raise LolgpsError(f"condition index must be >= 0, got {index}")
        arrays = _to_numpy(samples)
        for prefix, controller in (("cur", p_cur), ("pre", p_pre)):
            if controller is not None:
                for key, tensor in zip(("K", "k", "cov"), controller, strict=True):
                    arrays[f"{prefix}_{key}"] = tensor.detach().cpu().to(torch.float64).numpy()
        arrays.update(_visited_arrays(visited))
        name = _group_name(index)
        existing = self.path.exists()
        if existing:
            with self._open() as f:
                if name in f:
                    raise LolgpsError(f"replay {self.path} already holds condition {index}")
                self._check_sizes(f, arrays)

        def write(tmp: Path) -> None:
            if existing:
                shutil.copyfile(self.path, tmp)
            with h5py.File(tmp, "a" if existing else "w", libver="v110") as f:
                f.attrs["format"] = FORMAT
                f.attrs["version"] = VERSION
                group = f.create_group(name)
                group.attrs["condition"] = index
                group.attrs["offset"] = np.asarray(offset, dtype=np.float64)
                group.attrs["iterations"] = iterations
                for key, array in arrays.items():
                    group.create_dataset(
                        key,
                        data=array,
                        chunks=_chunks(key, array),
                        maxshape=(None, *array.shape[1:]),
                        compression="gzip",
                        fletcher32=True,
                    )

        atomic_write(self.path, write)  # a full disk: the previous file is kept

    def _check_sizes(self, f: h5py.File, arrays: dict[str, np.ndarray]) -> None:
        """New samples must have the state and action sizes of the stored ones."""
        for name in f:
            for key in ("x", "u"):
                stored, new = f[name][key].shape[-1], arrays[key].shape[-1]
                if stored != new:
                    raise LolgpsError(
                        f"replay {self.path} holds {key} of size {stored}, got size {new}"
                    )

    def read_condition(self, index: int, device: torch.device | str = "cpu") -> ConditionRecord:
        """One condition's attributes and raw tensors (float64, ``has_pre`` bool) on ``device``."""
        with self._open() as f:
            return self._read(f, index, device)

    def _read(self, f: h5py.File, index: int, device: torch.device | str) -> ConditionRecord:
        name = _group_name(index)
        if name not in f:
            raise LolgpsError(f"replay {self.path} holds no condition {index}")
        group = f[name]
        tensors = {
            key: torch.from_numpy(group[key][()]).to(device)
            for key in ConditionSamples._fields
            if key in group  # final_state is absent from groups written before it was stored
        }
        controllers = [_read_controller(group, prefix, device) for prefix in ("cur", "pre")]
        dx, dy = (float(v) for v in group.attrs["offset"])
        return ConditionRecord(
            condition=int(group.attrs["condition"]),
            offset=(dx, dy),
            iterations=int(group.attrs["iterations"]),
            samples=ConditionSamples(**tensors),
            p_cur=controllers[0],
            p_pre=controllers[1],
            visited=_read_visited(group, device),
        )

    def load(
        self, indices: list[int] | None = None, device: torch.device | str = "cpu"
    ) -> DistillBatch:
        """The S-step rows of the given conditions (default: all), flattened over samples and
        time and concatenated in the order given, as float64 tensors on ``device``."""
        if not self.path.exists():
            raise LolgpsError(f"replay {self.path} does not exist")
        with self._open() as f:
            if indices is None:
                indices = _stored_conditions(f)
            if not indices:
                raise LolgpsError(f"replay {self.path} holds no conditions")
            batches = [self._read(f, index, device).samples.to_batch() for index in indices]
        return DistillBatch(*(torch.cat(fields) for fields in zip(*batches, strict=True)))
