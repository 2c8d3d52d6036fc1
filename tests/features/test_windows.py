"""The search windows of eq. 20-34 on rectified and unrectified rigs: their geometry, the
paper's statement of them (the reference matcher's window test), and the vectorised
candidate search against an exhaustive one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cvslam_cli.features.windows import (
    _across_axis,
    _expand_ranges,
    _rig_geometry,
    _windows,
    auto_z_min_m,
    candidate_pairs,
    search_windows,
    undistort_keypoints,
)
from cvslam_cli.geometry.projection import project_points
from tests.features.reference_matcher import epipolar_residual_px, fundamental_matrix, in_window
from tests.features.rigs import BASELINE_M, RIGS, STACKED, F, H, K, W, to_right

ALL_RIGS = {**RIGS, "stacked": STACKED}


def test_undistort_keypoints_gives_ideal_pixels():
    cam = RIGS["unrectified"].left
    rng = np.random.default_rng(0)
    xy = rng.uniform([-0.7, -0.45], [0.7, 0.45], (200, 2))
    uv_raw, _ = project_points(cam, np.column_stack([xy, np.ones(200)]))
    ideal = undistort_keypoints(cam, uv_raw)
    np.testing.assert_allclose(ideal, xy * F + K[:2, 2], atol=1e-6)
    plain = RIGS["rectified"].left
    np.testing.assert_array_equal(undistort_keypoints(plain, uv_raw), uv_raw)
    assert undistort_keypoints(cam, np.zeros((0, 2))).shape == (0, 2)


def test_rectified_window_is_the_disparity_range():
    rig = RIGS["rectified"]
    uv = np.array([[400.0, 100.0], [20.0, 470.0]])
    z_min = auto_z_min_m(rig)
    assert z_min == pytest.approx(max(0.5, 4 * BASELINE_M))
    win = search_windows(uv, rig, z_min, 1.5)
    np.testing.assert_allclose(win.start_px, uv, atol=1e-9)  # zero disparity at infinity
    np.testing.assert_allclose(win.direction, [[-1.0, 0.0]] * 2, atol=1e-12)
    np.testing.assert_allclose(win.length_px, F * BASELINE_M / z_min)  # HD_max = f b / z_min
    assert auto_z_min_m(rig, 7.0) == 7.0


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_window_holds_the_right_projections_of_depths_beyond_z_min(rig_name: str):
    rig = RIGS[rig_name]
    rng = np.random.default_rng(1)
    n = 500
    uv_l = rng.uniform([0, 0], [W, H], (n, 2))
    ray = np.column_stack([(uv_l - K[:2, 2]) / F, np.ones(n)])
    z_min = 3.0
    win = search_windows(uv_l, rig, z_min, 0.1)
    idx = np.arange(n)
    for z, inside in ((z_min * 1.001, True), (7.0, True), (1e6, True), (z_min / 2, False)):
        p_r = to_right(rig, ray * z)
        uv_r = p_r[:, :2] / p_r[:, 2:3] * F + K[:2, 2]
        assert np.all(win.contains(idx, uv_r) == inside), z
        np.testing.assert_allclose(epipolar_residual_px(rig, uv_l, uv_r), 0.0, atol=1e-6)
    # x_r^T F x_l = 0
    p_r = to_right(rig, ray * 10.0)
    x_r = np.column_stack([p_r[:, :2] / p_r[:, 2:3] * F + K[:2, 2], np.ones(n)])
    x_l = np.column_stack([uv_l, np.ones(n)])
    Fm = fundamental_matrix(rig)
    assert np.abs(np.einsum("ij,jk,ik->i", x_r, Fm, x_l)).max() < 1e-9 * np.abs(Fm).max() * W


def test_row_windows_of_a_rectified_rig_equal_the_general_windows():
    rig = RIGS["rectified"]
    geo = _rig_geometry(rig)
    assert geo.rows_only and not _rig_geometry(RIGS["unrectified"]).rows_only
    uv = np.random.default_rng(6).uniform([0, 0], [W, H], (300, 2))
    rows = _windows(uv, geo, 3.0, 1.5)
    general = _windows(uv, dataclasses.replace(geo, rows_only=False), 3.0, 1.5)
    for name in ("start_px", "direction", "length_px"):
        np.testing.assert_allclose(getattr(rows, name), getattr(general, name), atol=1e-9)
    np.testing.assert_array_equal(rows.valid, general.valid)


@pytest.mark.parametrize("rig_name", list(ALL_RIGS))
@pytest.mark.parametrize(("z_min_m", "tolerance_px"), [(2.0, 3.0), (6.0, 0.5)])
def test_windows_are_the_papers_windows(rig_name: str, z_min_m: float, tolerance_px: float):
    """`SearchWindow.contains` against the plain statement of eq. 20-34 (`in_window`) on
    every pair of random left and right points, many of them near the windows."""
    rig = ALL_RIGS[rig_name]
    rng = np.random.default_rng(7)
    left = rng.uniform([0, 0], [W, H], (300, 2))
    depth = rng.uniform(0.5 * z_min_m, 50.0, 300)
    ray = np.column_stack([(left - K[:2, 2]) / F, np.ones(300)])
    p_r = to_right(rig, ray * depth[:, None])
    near = p_r[:, :2] / p_r[:, 2:3] * F + K[:2, 2] + rng.normal(0.0, tolerance_px, (300, 2))
    right = np.vstack([near, rng.uniform([0, 0], [W, H], (300, 2))])
    want = in_window(rig, z_min_m, tolerance_px, left, right)
    win = search_windows(left, rig, z_min_m, tolerance_px)
    all_l, all_r = (a.ravel() for a in np.meshgrid(np.arange(300), np.arange(600), indexing="ij"))
    got = win.contains(all_l, right[all_r]).reshape(300, 600)
    np.testing.assert_array_equal(got, want)
    assert 0.2 < want[np.arange(300), np.arange(300)].mean() < 0.95  # near the edges too


@pytest.mark.parametrize("rig_name", list(ALL_RIGS))
def test_vectorised_candidates_equal_the_exhaustive_search(rig_name: str):
    rig = ALL_RIGS[rig_name]
    rng = np.random.default_rng(2)
    left = rng.uniform([0, 0], [W, H], (400, 2))
    right = rng.uniform([-50, -20], [W + 50, H + 20], (3000, 2))
    win = search_windows(left, rig, 2.0, 3.0)
    li, rj = candidate_pairs(win, right)
    all_l, all_r = (a.ravel() for a in np.meshgrid(np.arange(400), np.arange(3000), indexing="ij"))
    inside = win.contains(all_l, right[all_r])
    expected = set(zip(all_l[inside].tolist(), all_r[inside].tolist(), strict=True))
    assert set(zip(li.tolist(), rj.tolist(), strict=True)) == expected
    assert len(li) == len(expected) > 100
    assert np.all(np.diff(li) >= 0)


def test_buckets_across_the_dominant_epipolar_direction():
    uv = np.random.default_rng(3).uniform([0, 0], [W, H], (50, 2))
    for rig, axis in ((RIGS["rectified"], 1), (RIGS["unrectified"], 1), (STACKED, 0)):
        assert _across_axis(search_windows(uv, rig, 2.0, 1.0).rows) == axis


def test_ranges_expand_into_pairs_in_window_order():
    left, pos = _expand_ranges(np.array([5, 0, 2]), np.array([2, 0, 3]))
    assert left.tolist() == [0, 0, 2, 2, 2] and pos.tolist() == [5, 6, 2, 3, 4]
    left, pos = _expand_ranges(np.array([1, 4]), np.array([0, 0]))
    assert left.shape == pos.shape == (0,)
