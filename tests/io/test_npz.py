"""Byte-reproducible .npz archives, written atomically."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.npz import NpzWriter, load_versioned_npz, save_npz


def test_same_arrays_same_bytes_readable_by_numpy(tmp_path):
    arrays = {"b": np.arange(5.0), "a": np.array("text")}
    save_npz(tmp_path / "1.npz", arrays)
    save_npz(tmp_path / "2.npz", dict(reversed(arrays.items())))
    assert (tmp_path / "1.npz").read_bytes() == (tmp_path / "2.npz").read_bytes()
    with np.load(tmp_path / "1.npz") as npz:
        assert npz.files == ["a", "b"]
        np.testing.assert_array_equal(npz["b"], arrays["b"])


def test_an_interrupted_writer_leaves_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt), NpzWriter(tmp_path / "depth.npz") as w:
        w.add("frame_000000", np.zeros((2, 2), np.float16))
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    with NpzWriter(tmp_path / "depth.npz") as w:
        w.add("frame_000000", np.zeros((2, 2), np.float16))
        assert [p.name for p in tmp_path.iterdir()] == ["depth.npz.partial"]
    assert [p.name for p in tmp_path.iterdir()] == ["depth.npz"]


def test_versioned_npz_checks_format_and_version(tmp_path):
    path = tmp_path / "a.npz"
    save_npz(path, {"format": np.array("thing"), "version": np.array(2), "x": np.arange(3)})
    data = load_versioned_npz(path, "thing", 2, "thing", "cvslam redo")
    np.testing.assert_array_equal(data["x"], np.arange(3))
    assert set(load_versioned_npz(path, "thing", 2, "thing", "cvslam redo", ("x",))) == {"x"}
    with pytest.raises(CvslamError, match=r"a\.npz: not a cvslam other file \(format 'thing'\)"):
        load_versioned_npz(path, "other", 2, "other", "cvslam redo")
    with pytest.raises(
        CvslamError, match=r"thing format version 2, .* version 3; run `cvslam redo`"
    ):
        load_versioned_npz(path, "thing", 3, "thing", "cvslam redo")
    with pytest.raises(CvslamError, match=r"not a readable thing file"):
        load_versioned_npz(path, "thing", 2, "thing", "cvslam redo", ("missing",))
    with pytest.raises(CvslamError, match=r"b\.npz: thing file not found"):
        load_versioned_npz(tmp_path / "b.npz", "thing", 2, "thing", "cvslam redo")
