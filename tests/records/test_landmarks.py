"""The landmark map record: conversion to the documented dtypes, refusal of bad shapes."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.records.landmarks import LandmarkMap


def five_landmarks() -> dict[str, object]:
    """The fields of a valid map of 5 landmarks, as plain Python / numpy values."""
    return {
        "landmark_id": [4, 0, 7, 2, 9],
        "p_nav_m": np.arange(15.0).reshape(5, 3),
        "std_m": np.array([[0.1, 0.2, 0.3]] * 4 + [[0.5, 0.1, 0.1]]),
        "observers": ("uav1", "uav2", "uav1;uav2", "uav1", "uav2"),
        "n_observations": [3, 1, 8, 2, 5],
        "first_seen_ns": [10, 20, 30, 40, 50],
        "last_seen_ns": [11, 21, 39, 40, 90],
        "in_state": [True, False, True, True, False],
        "true_id": [12, -1, -2, 3, 4],
    }


def test_arrays_are_converted_to_the_documented_dtypes():
    lm = LandmarkMap(**five_landmarks())
    assert len(lm) == 5
    for name in ("landmark_id", "n_observations", "first_seen_ns", "last_seen_ns", "true_id"):
        assert getattr(lm, name).dtype == np.int64, name
    assert lm.p_nav_m.dtype == np.float64 and lm.in_state.dtype == np.bool_
    np.testing.assert_array_equal(lm.max_std_m, [0.3, 0.3, 0.3, 0.3, 0.5])


def test_empty_map_accepts_empty_lists():
    empty = {k: [] for k in five_landmarks()}
    lm = LandmarkMap(**{**empty, "p_nav_m": np.zeros((0, 3)), "std_m": np.zeros((0, 3))})
    assert len(lm) == 0 and lm.landmark_id.dtype == np.int64 and lm.max_std_m.shape == (0,)


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        (
            "p_nav_m",
            np.zeros((4, 2)),
            r"LandmarkMap.p_nav_m: expected real numbers of shape \(N, 3\) = \(5, 3\), "
            r"got float64 of shape \(4, 2\)",
        ),
        ("std_m", np.zeros(5), r"std_m: expected real numbers of shape \(N, 3\) = \(5, 3\)"),
        ("observers", ("uav1",) * 4, "observers: expected 5 strings"),
        ("n_observations", np.zeros(5), "n_observations: expected integers"),
        ("in_state", np.zeros(5, int), "in_state: expected booleans"),
        ("last_seen_ns", np.zeros(6, np.int64), r"last_seen_ns: expected .* \(N,\) = \(5,\)"),
        ("true_id", np.zeros(4, np.int64), r"true_id: expected .* \(N,\) = \(5,\)"),
        ("landmark_id", np.array([1, 2, 3, 2, 5]), "id 2 appears more than once"),
        (
            "landmark_id",
            np.zeros((5, 1), np.int64),
            r"landmark_id: expected integers of shape \(N,\), got int64 of shape \(5, 1\)",
        ),
    ],
)
def test_bad_fields_are_refused_saying_what_was_expected(field, value, expected):
    with pytest.raises(ValueError, match=expected):
        LandmarkMap(**{**five_landmarks(), field: value})
