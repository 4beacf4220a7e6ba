"""sellip.jobs' atomic writers: an output appears whole or not at all, an old one is replaced in one step, an error
leaves the old output and no temporary behind, and the temporary keeps the output's suffix (writers that choose
the format by it: numpy's .npz, imageio's .png)."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.jobs import atomic_directory, atomic_file, write_text


def test_atomic_file_appears_whole_and_keeps_the_suffix(tmp_path):
    output = tmp_path / "sub" / "shard.npz"
    with atomic_file(output) as tmp:
        assert tmp.parent == output.parent and tmp.suffix == ".npz" and tmp.name.startswith(".")
        np.savez(tmp, a=np.arange(3))
        assert not output.exists()
        assert tmp.exists()  # numpy did not add a second suffix
    with np.load(output) as data:
        assert data["a"].tolist() == [0, 1, 2]
    assert sorted(p.name for p in output.parent.iterdir()) == ["shard.npz"]


def test_an_error_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    output = write_text("old", tmp_path / "metrics.json")
    with pytest.raises(RuntimeError):
        with atomic_file(output) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert output.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]
    write_text("new", output)
    assert output.read_text() == "new"


def test_atomic_directory_replaces_the_old_one_or_leaves_it(tmp_path):
    output = tmp_path / "params.zarr"
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        (tmp / "a").write_text("1")
    with pytest.raises(ValueError):
        with atomic_directory(output) as tmp:
            tmp.mkdir()
            (tmp / "b").write_text("2")
            raise ValueError("bad")
    assert sorted(p.name for p in output.iterdir()) == ["a"]
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        (tmp / "b").write_text("2")
    assert sorted(p.name for p in output.iterdir()) == ["b"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.zarr"]
