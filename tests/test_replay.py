"""The HDF5 replay: round trips, append-only atomic writes, corrupt files."""

from __future__ import annotations

import multiprocessing
import os
import signal
from pathlib import Path
from typing import Any

import h5py
import pytest
import torch

from lolgps_torch.data import ReplayBuffer
from lolgps_torch.errors import LolgpsError
from lolgps_torch.types import ConditionSamples, LinearGaussian

F64 = torch.float64


def make_samples(
    M: int, T: int, dX: int, dU: int, has_pre: bool, seed: int, final: bool = True
) -> ConditionSamples:
    """Random samples; without ``final``, no final state (as replays written before it)."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(M, T, dU, dU, dtype=F64, generator=g)
    pre = float(has_pre)
    return ConditionSamples(
        x=torch.randn(M, T, dX, dtype=F64, generator=g),
        u=torch.randn(M, T, dU, dtype=F64, generator=g),
        cost=torch.rand(M, T, dtype=F64, generator=g),
        final_distance=torch.rand(M, dtype=F64, generator=g),
        mean_cur=torch.randn(M, T, dU, dtype=F64, generator=g),
        prec_cur=A @ A.mT + torch.eye(dU, dtype=F64),
        mean_pre=pre * torch.randn(M, T, dU, dtype=F64, generator=g),
        prec_pre=pre * (A.mT @ A + torch.eye(dU, dtype=F64)),
        has_pre=torch.full((M,), has_pre),
        final_state=torch.randn(M, dX, dtype=F64, generator=g) if final else None,
    )


def assert_samples_equal(a: ConditionSamples, b: ConditionSamples) -> None:
    for name, x, y in zip(ConditionSamples._fields, a, b, strict=True):
        if x is None or y is None:
            assert x is None and y is None, name
        else:
            assert x.dtype == y.dtype and torch.equal(x, y), name


@pytest.fixture
def two_conditions() -> tuple[ConditionSamples, ConditionSamples]:
    return make_samples(3, 5, 4, 2, False, 0, final=False), make_samples(2, 5, 4, 2, True, 1)


def raw_group(path: Path, name: str) -> dict[str, tuple[bytes, list[bytes]]]:
    """Each dataset's decoded bytes and its compressed chunks as stored on disk."""
    out = {}
    with h5py.File(path, "r") as f:
        for key, ds in f[name].items():
            chunks = [
                ds.id.read_direct_chunk(ds.id.get_chunk_info(i).chunk_offset)[1]
                for i in range(ds.id.get_num_chunks())
            ]
            out[key] = (ds[()].tobytes(), chunks)
    return out


def test_round_trip_of_two_conditions(tmp_path: Path, two_conditions: tuple) -> None:
    first, second = two_conditions
    replay = ReplayBuffer(tmp_path / "replay.h5")
    assert replay.conditions() == []
    replay.append_condition(0, (0.02, -0.02), first, iterations=7)
    replay.append_condition(1, (0.1, 0.0), second, iterations=4)
    assert replay.conditions() == [0, 1]
    assert replay.offsets() == [(0.02, -0.02), (0.1, 0.0)]
    record = replay.read_condition(1)
    assert (record.condition, record.offset, record.iterations) == (1, (0.1, 0.0), 4)
    assert_samples_equal(record.samples, second)
    assert_samples_equal(replay.read_condition(0).samples, first)
    batch = replay.load()
    assert batch.x.shape == (5 * 5, 4) and batch.prec_pre.shape == (25, 2, 2)
    assert torch.equal(batch.x, torch.cat([first.x.reshape(-1, 4), second.x.reshape(-1, 4)]))
    assert torch.equal(batch.has_pre, torch.arange(25) >= 15)
    only_second = replay.load([1])
    for got, want in zip(only_second, second.to_batch(), strict=True):
        assert torch.equal(got, want)
    with h5py.File(tmp_path / "replay.h5", "r") as f:
        ds = f["condition_000/prec_cur"]
        assert ds.compression == "gzip" and ds.chunks == (1, 5, 2, 2) and ds.dtype == "float64"


def test_controllers_round_trip_and_are_optional(tmp_path: Path, two_conditions: tuple) -> None:
    first, second = two_conditions
    g = torch.Generator().manual_seed(2)
    A = torch.randn(5, 2, 2, dtype=F64, generator=g)
    p_cur = LinearGaussian(
        torch.randn(5, 2, 4, dtype=F64, generator=g),
        torch.randn(5, 2, dtype=F64, generator=g),
        A @ A.mT + torch.eye(2, dtype=F64),
    )
    replay = ReplayBuffer(tmp_path / "replay.h5")
    replay.append_condition(0, (0.0, 0.0), first, iterations=1, p_cur=p_cur)
    replay.append_condition(1, (0.0, 0.0), second, iterations=1)
    stored = replay.read_condition(0)
    assert stored.p_cur is not None and stored.p_pre is None
    for got, want in zip(stored.p_cur, p_cur, strict=True):
        assert torch.equal(got, want)
    assert replay.read_condition(1).p_cur is None


def test_a_condition_without_successes_is_stored(tmp_path: Path) -> None:
    replay = ReplayBuffer(tmp_path / "replay.h5")
    replay.append_condition(0, (0.0, 0.0), make_samples(0, 5, 4, 2, False, seed=0), iterations=20)
    assert replay.conditions() == [0] and replay.load().x.shape == (0, 4)


def test_earlier_groups_stay_byte_identical(tmp_path: Path, two_conditions: tuple) -> None:
    first, second = two_conditions
    path = tmp_path / "replay.h5"
    replay = ReplayBuffer(path)
    replay.append_condition(0, (0.0, 0.0), first, iterations=1)
    before = raw_group(path, "condition_000")
    replay.append_condition(1, (0.0, 0.0), second, iterations=1)
    assert raw_group(path, "condition_000") == before
    assert not (tmp_path / "replay.h5.partial").exists()


def test_writing_an_existing_condition_raises(tmp_path: Path, two_conditions: tuple) -> None:
    first, second = two_conditions
    path = tmp_path / "replay.h5"
    replay = ReplayBuffer(path)
    replay.append_condition(0, (0.0, 0.0), first, iterations=1)
    data = path.read_bytes()
    with pytest.raises(LolgpsError, match="already holds condition 0"):
        replay.append_condition(0, (0.0, 0.0), second, iterations=1)
    assert path.read_bytes() == data


def test_mismatched_sizes_raise(tmp_path: Path, two_conditions: tuple) -> None:
    replay = ReplayBuffer(tmp_path / "replay.h5")
    replay.append_condition(0, (0.0, 0.0), two_conditions[0], iterations=1)
    with pytest.raises(LolgpsError, match="size"):
        replay.append_condition(1, (0.0, 0.0), make_samples(2, 5, 6, 2, True, 3), iterations=1)
    bad = two_conditions[1]._replace(cost=torch.zeros(2, 4, dtype=F64))
    with pytest.raises(LolgpsError, match="cost has shape"):
        replay.append_condition(1, (0.0, 0.0), bad, iterations=1)


@pytest.mark.parametrize("keep", [0.5, 0.98, 100])
def test_truncated_file_raises(tmp_path: Path, two_conditions: tuple, keep: float) -> None:
    path = tmp_path / "replay.h5"
    replay = ReplayBuffer(path)
    replay.append_condition(0, (0.0, 0.0), two_conditions[0], iterations=1)
    data = path.read_bytes()
    path.write_bytes(data[: int(keep if keep > 1 else keep * len(data))])
    for read in (replay.conditions, replay.load):
        with pytest.raises(LolgpsError, match="cannot read replay") as info:
            read()
        assert "\n" not in str(info.value)
    with pytest.raises(LolgpsError, match="cannot read replay"):
        replay.append_condition(1, (0.0, 0.0), two_conditions[1], iterations=1)


def test_a_flipped_bit_in_stored_data_raises(tmp_path: Path, two_conditions: tuple) -> None:
    path = tmp_path / "replay.h5"
    replay = ReplayBuffer(path)
    replay.append_condition(0, (0.0, 0.0), two_conditions[0], iterations=1)
    with h5py.File(path, "r") as f:
        chunk = f["condition_000/x"].id.get_chunk_info(1)
    data = bytearray(path.read_bytes())
    data[chunk.byte_offset + chunk.size // 2] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(LolgpsError, match="cannot read replay"):
        replay.load()


def test_crash_during_append_leaves_the_file_intact(
    tmp_path: Path, two_conditions: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    first, second = two_conditions
    path = tmp_path / "replay.h5"
    replay = ReplayBuffer(path)
    replay.append_condition(0, (0.0, 0.0), first, iterations=1)
    data = path.read_bytes()
    real = h5py.Group.create_dataset
    calls = []

    def failing(self: h5py.Group, *args: object, **kwargs: object) -> h5py.Dataset:
        calls.append(args[0])
        if len(calls) == 4:
            raise RuntimeError("simulated crash")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing)
    with pytest.raises(RuntimeError, match="simulated crash"):
        replay.append_condition(1, (0.0, 0.0), second, iterations=1)
    assert path.read_bytes() == data
    assert replay.conditions() == [0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["replay.h5"]
    # A crash while writing the very first group leaves no file at all.
    calls.clear()
    fresh = ReplayBuffer(tmp_path / "fresh.h5")
    with pytest.raises(RuntimeError, match="simulated crash"):
        fresh.append_condition(0, (0.0, 0.0), first, iterations=1)
    assert fresh.conditions() == [] and not fresh.path.exists()


def _append_killed_at_the_fifth_dataset(path: Path, samples: ConditionSamples) -> None:
    """Append ``samples`` as condition 1 and SIGKILL this process as the append creates its
    fifth dataset, the file flushed first."""
    real = h5py.Group.create_dataset
    calls = []

    def killing(self: h5py.Group, *args: Any, **kwargs: Any) -> h5py.Dataset:
        calls.append(1)
        if len(calls) == 5:
            self.file.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        return real(self, *args, **kwargs)

    h5py.Group.create_dataset = killing
    ReplayBuffer(path).append_condition(1, (0.0, 0.0), samples, iterations=1)


def test_sigkill_during_append_leaves_the_file_intact(
    tmp_path: Path, two_conditions: tuple
) -> None:
    first, second = two_conditions
    path = tmp_path / "replay.h5"
    replay = ReplayBuffer(path)
    replay.append_condition(0, (0.0, 0.0), first, iterations=1)
    data = path.read_bytes()
    writer = multiprocessing.get_context("fork").Process(
        target=_append_killed_at_the_fifth_dataset, args=(path, second)
    )
    writer.start()
    writer.join(timeout=300)
    assert writer.exitcode == -signal.SIGKILL
    assert path.read_bytes() == data
    assert replay.conditions() == [0]
    assert (tmp_path / "replay.h5.partial").exists()  # the killed writer's leftover
    replay.append_condition(1, (0.0, 0.0), second, iterations=1)
    assert replay.conditions() == [0, 1] and not (tmp_path / "replay.h5.partial").exists()
    assert_samples_equal(replay.read_condition(1).samples, second)
