"""The feature set record: the builder's offsets and dtypes, and `validate`'s refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cvslam_cli.records.features import FeatureSetBuilder
from tests.synth import feature_rig, feature_set


def test_builder_offsets_and_global_indices():
    fs = feature_set()
    assert fs.n_frames == 3
    assert fs.left_offsets.tolist() == [0, 5, 5, 12]
    assert fs.match_offsets.tolist() == [0, 3, 3, 7]
    third = fs.frame_matches(2)
    assert np.all(fs.match_left[third] >= 5) and np.all(fs.match_right[third] >= 6)
    assert fs.left_desc.dtype == np.uint8 and fs.match_cov_cam_m2.shape == (7, 3, 3)
    assert fs.right_octave.dtype == np.int32 and fs.match_landmark_id.dtype == np.int64


def test_builder_without_frames_gives_empty_columns_of_the_right_shapes():
    fs = FeatureSetBuilder("uav1", feature_rig()).build()
    assert fs.n_frames == 0 and fs.match_offsets.tolist() == [0]
    assert fs.left_desc.shape == (0, 128) and fs.left_desc.dtype == np.uint8
    assert fs.match_p_cam_m.shape == (0, 3) and fs.right_uv_px.dtype == np.float32


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        (
            "left_desc",
            lambda fs: fs.left_desc.astype(np.uint16),
            r"left_desc: expected uint8 of shape \(NL, 128\) = \(12, 128\), got uint16",
        ),
        (
            "right_uv_px",
            lambda fs: fs.right_uv_px[:, :1],
            r"right_uv_px: expected float32 of shape \(NR, 2\) = \(10, 2\), got float32 of "
            r"shape \(10, 1\)",
        ),
        (
            "match_ratio",
            lambda fs: fs.match_ratio[:-1],
            r"match_ratio: expected float32 of shape \(M,\) = \(7,\)",
        ),
        (
            "match_offsets",
            lambda fs: fs.match_offsets[:-1],
            r"match_offsets: expected integers of shape \(F\+1,\) = \(4,\)",
        ),
        (
            "match_offsets",
            lambda fs: np.array([0, 3, 2, 7]),
            "match_offsets must be non-decreasing from 0",
        ),
        ("match_left", lambda fs: fs.match_left + 12, "match indices point past"),
        ("frame_stamp_ns", lambda fs: fs.frame_stamp_ns[::-1].copy(), "expected in time order"),
    ],
)
def test_validate_refuses_inconsistent_sets(field, value, expected):
    fs = feature_set()
    bad = dataclasses.replace(fs, **{field: value(fs)})
    with pytest.raises(ValueError, match=expected):
        bad.validate()


def test_validate_checks_the_rig():
    fs = feature_set()
    rig = dataclasses.replace(fs.rig, D=np.zeros((2, 4)))
    with pytest.raises(ValueError, match=r"rig.D: expected real numbers of shape \(2, 5\)"):
        dataclasses.replace(fs, rig=rig).validate()
