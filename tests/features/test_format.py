"""The feature file format: builder, round trip, refusal of other versions and corrupt data."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.features.format import FeatureSetBuilder, RigCalibration
from cvslam_cli.io.features_file import load_features, save_features


def _rig() -> RigCalibration:
    K = np.array([[450.0, 0, 376], [0, 450, 240], [0, 0, 1]])
    T = np.stack([np.eye(4), np.eye(4)])
    T[1, 0, 3] = 0.5
    return RigCalibration(
        K=np.stack([K, K]),
        D=np.zeros((2, 5)),
        distortion_model="plumb_bob",
        T_body_cam=T,
        size_px=np.array([[752, 480], [752, 480]]),
    )


def _side(rng, n):
    return {
        "uv_raw_px": rng.uniform(0, 700, (n, 2)),
        "uv_px": rng.uniform(0, 700, (n, 2)),
        "size_px": rng.uniform(1, 9, n),
        "angle_deg": rng.uniform(0, 360, n),
        "response": rng.uniform(0, 1, n),
        "octave": rng.integers(0, 4, n),
        "desc": rng.integers(0, 256, (n, 128)),
    }


def _matches(rng, m, nl, nr):
    return {
        "left": rng.integers(0, nl, m),
        "right": rng.integers(0, nr, m),
        "disparity_px": rng.uniform(0, 30, m),
        "distance": rng.uniform(0, 300, m),
        "ratio": rng.uniform(0, 0.8, m),
        "p_cam_m": rng.normal(size=(m, 3)),
        "cov_cam_m2": np.tile(np.eye(3), (m, 1, 1)),
        "landmark_id": rng.integers(-2, 50, m),
    }


def build(seed=0):
    rng = np.random.default_rng(seed)
    b = FeatureSetBuilder("uav1", _rig())
    for i, (nl, nr, m) in enumerate([(5, 6, 3), (0, 0, 0), (7, 4, 4)]):
        b.add_frame(
            1000 + i, _side(rng, nl), _side(rng, nr), _matches(rng, m, max(nl, 1), max(nr, 1))
        )
    return b.build()


def test_builder_offsets_and_global_indices():
    fs = build()
    assert fs.n_frames == 3
    assert fs.left_offsets.tolist() == [0, 5, 5, 12]
    assert fs.match_offsets.tolist() == [0, 3, 3, 7]
    third = fs.frame_matches(2)
    assert np.all(fs.match_left[third] >= 5) and np.all(fs.match_right[third] >= 6)
    assert fs.left_desc.dtype == np.uint8 and fs.match_cov_cam_m2.shape == (7, 3, 3)


def test_round_trip(tmp_path):
    fs = build()
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
    fs = build()
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

    save_features(build(), tmp_path / "a.npz", {"x": 1})
    time.sleep(1.1)  # numpy.savez would stamp a different time into the zip
    save_features(build(), tmp_path / "b.npz", {"x": 1})
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
