"""Feature files: round trip, byte reproducibility, refusal of other versions and corrupt data."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.features_file import load_features, save_features
from tests.synth import feature_set


def test_round_trip(tmp_path):
    fs = feature_set()
    save_features(fs, tmp_path / "uav1.npz", {"source": "test"})
    back, meta = load_features(tmp_path / "uav1.npz")
    assert meta == {"source": "test"} and back.vehicle == "uav1"
    for f in fields(fs):
        if f.name not in ("vehicle", "rig"):
            a, b = getattr(fs, f.name), getattr(back, f.name)
            assert a.dtype == b.dtype, f.name
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.rig.T_body_cam, fs.rig.T_body_cam)
    assert not list(tmp_path.glob("*.partial"))


def test_other_version_and_corrupt_files_refused(tmp_path):
    fs = feature_set()
    path = tmp_path / "f.npz"
    save_features(fs, path, {})
    data = dict(np.load(path))
    data["version"] = np.array(99)
    np.savez(tmp_path / "v99.npz", **data)
    with pytest.raises(CvslamError, match="feature format version 99"):
        load_features(tmp_path / "v99.npz")
    data["version"] = np.array(1)
    data["match_offsets"] = np.array([0, 3, 2, 7])
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(CvslamError, match="corrupt feature file"):
        load_features(tmp_path / "bad.npz")
    (tmp_path / "junk.npz").write_text("junk")
    with pytest.raises(CvslamError, match="not a readable feature file"):
        load_features(tmp_path / "junk.npz")


def test_files_are_byte_reproducible(tmp_path):
    import time

    save_features(feature_set(), tmp_path / "a.npz", {"x": 1})
    time.sleep(1.1)  # numpy.savez would stamp a different time into the zip
    save_features(feature_set(), tmp_path / "b.npz", {"x": 1})
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
