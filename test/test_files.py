"""`files.atomic_write`, the project's one atomic writer (checkpoints, run state, the protocol's
instance cache, the demonstration shards): the old file or the whole new one, never a part."""

import pytest

from mapf_fleet.files import TMP_MARK, atomic_write


def test_writes_bytes_or_through_a_callable(tmp_path):
    target = tmp_path / "sub" / "a.bin"
    assert atomic_write(target, b"first") == target
    assert target.read_bytes() == b"first"
    atomic_write(target, lambda handle: handle.write(b"second"))
    assert target.read_bytes() == b"second"
    assert not list(tmp_path.rglob(f"*{TMP_MARK}*"))


def test_a_failing_writer_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a.bin"
    atomic_write(target, b"old")

    def half(handle):
        handle.write(b"half of the new")
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError, match="killed mid-write"):
        atomic_write(target, half)
    assert target.read_bytes() == b"old"
    assert not list(tmp_path.glob(f"*{TMP_MARK}*"))


def test_the_protocol_cache_and_the_dagger_shards_use_it(monkeypatch, tmp_path):
    """The protocol cache and DAgger's shards go through `files.atomic_write` (which fsyncs)."""
    import numpy as np

    from mapf_fleet import files
    from mapf_fleet.evaluation import protocol
    from mapf_fleet.training.dagger import data as dagger_data

    written = []
    real = files.atomic_write

    def spy(path, write):
        written.append(path.name)
        return real(path, write)

    monkeypatch.setattr(files, "atomic_write", spy)
    monkeypatch.setattr(dagger_data, "atomic_write", spy)
    grid = np.zeros((1, 4, 4), np.uint8)
    cells = np.zeros((1, 1, 2), np.int64)
    protocol._write_npz_atomic(tmp_path / "cache.npz", grid, cells, cells)
    dagger_data.write_shard(tmp_path / "shard.npz", {"x": np.arange(3)}, {"file": "shard.npz"})
    assert written == ["cache.npz", "shard.npz"]
    assert np.load(tmp_path / "cache.npz")["maps"].shape == (1, 4, 4)
