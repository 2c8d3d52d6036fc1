"""Stereo-constrained matching (eq. 20-34): window geometry on rectified and unrectified
rigs, the vectorised candidate search against an exhaustive one, the vectorised matcher
against a straightforward reference (per-keypoint loops), precision on rendered stereo pairs
with known correspondences, and epipolar consistency on EuRoC and KITTI."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from cvslam_cli.config import AdaptiveSiftConfig, SiftConfig, StereoMatchConfig
from cvslam_cli.features.matching import (
    LONE_D2_QUANTILE,
    MIN_WINDOWS_FOR_TYPICAL_D2,
    StereoMatches,
    _quantile_f32,
    _rig_geometry,
    _windows,
    auto_z_min_m,
    candidate_pairs,
    epipolar_residual_px,
    fundamental_matrix,
    match_brute_force,
    match_stereo,
    search_windows,
    undistort_keypoints,
)
from cvslam_cli.features.sift import Keypoints, detect_and_describe
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.projection import pixel_rays, project_points, undistort_pixels
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, invert_T, make_T
from cvslam_cli.geometry.stereo import projection_matrices, triangulate
from cvslam_cli.sim.render import photometric
from cvslam_cli.sim.terrain import Terrain, TerrainSpec, make_terrain, render_terrain_view

W, H, F = 752, 480, 450.0
K = np.array([[F, 0.0, 376.0], [0.0, F, 240.0], [0.0, 0.0, 1.0]])
BASELINE_M = 1.0
# camera x -> body right, y -> body backwards, z -> body down: a nadir camera
R_BODY_CAM = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
SIFT, ADAPTIVE, MATCH = SiftConfig(), AdaptiveSiftConfig(), StereoMatchConfig()


def _rotation_deg(axis: list[float], deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    R, _ = cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))
    return R


def _camera(D: list[float] | None = None, T_body_cam: np.ndarray | None = None) -> CameraModel:
    T = np.eye(4) if T_body_cam is None else T_body_cam
    if D is None:
        return CameraModel(W, H, K.copy(), T_body_cam=T)
    return CameraModel(
        W, H, K.copy(), D=np.asarray(D, float), distortion_model="plumb_bob", T_body_cam=T
    )


RIGS = {
    "rectified": StereoRig(
        _camera(), _camera(T_body_cam=make_T(np.eye(3), np.array([BASELINE_M, 0.0, 0.0])))
    ),
    # 2 degrees of relative rotation, an off-axis baseline, different lens distortion
    "unrectified": StereoRig(
        _camera([-0.25, 0.07, 0.001, -0.0005, 0.0]),
        _camera(
            [-0.22, 0.05, -0.0008, 0.0004, 0.0],
            make_T(_rotation_deg([0.3, 1.0, 0.2], 2.0), np.array([BASELINE_M, 0.02, 0.01])),
        ),
    ),
}


def _T_right_left(rig: StereoRig) -> np.ndarray:
    return invert_T(rig.T_left_right)


def _to_right(rig: StereoRig, p_left: np.ndarray) -> np.ndarray:
    T = _T_right_left(rig)
    return p_left @ T[:3, :3].T + T[:3, 3]


# -- geometry ------------------------------------------------------------------------------


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
        p_r = _to_right(rig, ray * z)
        uv_r = p_r[:, :2] / p_r[:, 2:3] * F + K[:2, 2]
        assert np.all(win.contains(idx, uv_r) == inside), z
        np.testing.assert_allclose(epipolar_residual_px(rig, uv_l, uv_r), 0.0, atol=1e-6)
    # x_r^T F x_l = 0
    p_r = _to_right(rig, ray * 10.0)
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


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_vectorised_candidates_equal_the_exhaustive_search(rig_name: str):
    rig = RIGS[rig_name]
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


def test_empty_inputs():
    rig = RIGS["rectified"]
    none = np.zeros((0, 2))
    d0 = np.zeros((0, 128), np.uint8)
    some = np.array([[10.0, 10.0]])
    d1 = np.zeros((1, 128), np.uint8)
    for a, da, b, db in ((none, d0, some, d1), (some, d1, none, d0), (none, d0, none, d0)):
        m = match_stereo(a, da, b, db, rig, MATCH)
        assert len(m) == 0 and m.n_left == len(a) and m.n_right == len(b)
        assert len(match_brute_force(da, db, 0.7)) == 0
    with pytest.raises(ValueError, match="descriptors"):
        match_stereo(some, d0, some, d1, rig, MATCH)


def test_ratio_test_and_left_right_check_on_toy_descriptors():
    rig = RIGS["rectified"]
    left = np.array([[300.0, 100.0], [300.0, 200.0], [310.0, 200.0]])
    right = np.array([[290.0, 100.0], [280.0, 100.5], [295.0, 200.0], [500.0, 300.0]])
    base = np.zeros((4, 128), np.float32)
    base[:, :4] = 100 * np.eye(4)
    ld = np.stack([base[0], base[2], base[2] + 1.0]).astype(np.uint8)
    rd = np.stack([base[0] + 1.0, base[1], base[2], base[3]]).astype(np.uint8)
    m = match_stereo(left, ld, right, rd, rig, MATCH)
    # left 0: two candidates (right 0 and 1), right 0 is far better -> ratio test passes;
    # left 1 and 2 both want right 2 alone: left-right check keeps the better one (left 1)
    assert m.left.tolist() == [0, 1] and m.right.tolist() == [0, 2]
    np.testing.assert_allclose(m.disparity_px, [10.0, 5.0])
    assert m.ratio[0] > 0 and m.ratio[1] == 0  # right 2 was left 1's only candidate
    # (0,0), (0,1), (1,2), (2,2), and with < 8 multi-candidate windows the typical unrelated
    # distance for lone candidates comes from min(64, 3 x 4) spread-out pairs
    assert m.candidates_examined == 4 + 12
    loose = match_stereo(
        left, ld, right, rd, rig, dataclasses.replace(MATCH, left_right_check=False)
    )
    assert loose.left.tolist() == [0, 1, 2]


# -- the vectorised matcher against a straightforward reference ---------------------------


def _reference_match(
    luv: np.ndarray,
    ld: np.ndarray,
    ruv: np.ndarray,
    rd: np.ndarray,
    rig: StereoRig,
    cfg: StereoMatchConfig,
) -> StereoMatches:
    """The matcher's rules written plainly: every (left, right) pair through
    `SearchWindow.contains`, then a loop per left keypoint (sort of its candidates'
    distances: D1, D2, ratio test) and per right keypoint (its nearest left keypoint; equal
    distances go to the first left index). Distances in float64 and rounded once to float32
    (sqrt of an integer: the same as float32 arithmetic), the ratio test in float32 as the
    matcher does it."""
    n, m = len(luv), len(ruv)
    if n == 0 or m == 0:
        return StereoMatches.empty(n, m)
    win = search_windows(luv, rig, auto_z_min_m(rig, cfg.z_min_m), cfg.vertical_tolerance_px)
    all_l, all_r = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(m), indexing="ij"))
    inside = win.contains(all_l, ruv[all_r])
    li, rj = all_l[inside], all_r[inside]
    if len(li) == 0:
        return StereoMatches.empty(n, m)

    def distances(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        diff = ld[i].astype(np.float64) - rd[j].astype(np.float64)
        return np.sqrt((diff**2).sum(axis=1)).astype(np.float32)

    dist = distances(li, rj)
    examined = len(li)
    best: dict[int, tuple[int, np.float32, np.float32 | None]] = {}  # left -> (right, D1, D2)
    for i in np.unique(li):
        mine = np.flatnonzero(li == i)
        order = np.argsort(dist[mine], kind="stable")
        d2 = dist[mine[order[1]]] if len(mine) > 1 else None
        best[int(i)] = (int(rj[mine[order[0]]]), dist[mine[order[0]]], d2)
    multi = np.array([b[2] for b in best.values() if b[2] is not None], np.float32)
    if len(multi) >= MIN_WINDOWS_FOR_TYPICAL_D2:
        typical = np.float32(np.quantile(multi, LONE_D2_QUANTILE))
    else:
        k = min(64, n * m)
        i = np.arange(k)
        unrelated = distances((i * n) // k, (i * 7919 + m // 2) % m)
        typical = np.float32(np.quantile(unrelated, LONE_D2_QUANTILE))
        examined += k
    nearest_left = {}
    for j in np.unique(rj):
        mine = np.flatnonzero(rj == j)
        nearest_left[int(j)] = int(li[mine[np.lexsort((li[mine], dist[mine]))[0]]])
    rows = []
    for i, (j, d1, d2) in best.items():
        lone = d2 is None
        if not d1 < cfg.dist_ratio * (typical if lone else d2):
            continue
        if cfg.left_right_check and nearest_left[j] != i:
            continue
        ratio = np.float32(0.0) if lone else d1 / d2
        rows.append((i, j, np.float32(luv[i, 0] - ruv[j, 0]), d1, ratio))
    if not rows:
        return StereoMatches.empty(n, m, examined)
    left, right, disparity, distance, ratio = (list(c) for c in zip(*rows, strict=True))
    return StereoMatches(
        np.array(left, np.int64),
        np.array(right, np.int64),
        np.array(disparity, np.float32),
        np.array(distance, np.float32),
        np.array(ratio, np.float32),
        examined,
        n,
        m,
    )


def _assert_same_matches(got: StereoMatches, want: StereoMatches, exact: bool = True) -> None:
    """The same matches; distances and ratios bit for bit when `exact` (integer descriptors),
    else to float32 rounding (the summation order of non-integer squares differs)."""
    for name in ("left", "right", "disparity_px", "distance", "ratio"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype, name
        if exact or name in ("left", "right", "disparity_px"):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            np.testing.assert_allclose(a, b, rtol=1e-6, err_msg=name)
    assert got.candidates_examined == want.candidates_examined
    assert (got.n_left, got.n_right) == (want.n_left, want.n_right)


def _random_scene(
    rig: StereoRig,
    seed: int,
    n_true: int = 150,
    n_other: int = 120,
    n_dup: int = 8,
    dtype: type = np.uint8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Left and right keypoints (ideal pixels) and descriptors: `n_true` points at depths of
    2-60 m seen by both cameras (right descriptor = left + noise), `n_other` unrelated
    keypoints in each image, and exact duplicates (same position and descriptor) of `n_dup`
    keypoints on each side, which make equal distances (ties)."""
    rng = np.random.default_rng(seed)
    uv_l = rng.uniform([0, 0], [W, H], (n_true, 2))
    xy = undistort_pixels(rig.left, uv_l)
    depth = rng.uniform(2.0, 60.0, n_true)
    p_right = _to_right(rig, np.column_stack([xy, np.ones(n_true)]) * depth[:, None])
    uv_r = p_right[:, :2] / p_right[:, 2:3] @ rig.right.K[:2, :2].T + rig.right.K[:2, 2]
    uv_l = undistort_keypoints(rig.left, uv_l)
    uv_r += rng.normal(0.0, 0.3, uv_r.shape)
    desc_l = rng.integers(0, 120, (n_true, 128))
    desc_r = np.clip(desc_l + rng.integers(-12, 13, desc_l.shape), 0, 255)
    left = np.vstack([uv_l, rng.uniform([0, 0], [W, H], (n_other, 2))])
    right = np.vstack([uv_r, rng.uniform([0, 0], [W, H], (n_other, 2))])
    ld = np.vstack([desc_l, rng.integers(0, 120, (n_other, 128))])
    rd = np.vstack([desc_r, rng.integers(0, 120, (n_other, 128))])
    dup_l, dup_r = (
        rng.choice(n_true, n_dup, replace=False),
        rng.choice(n_true, n_dup, replace=False),
    )
    left, ld = np.vstack([left, left[dup_l]]), np.vstack([ld, ld[dup_l]])
    right, rd = np.vstack([right, right[dup_r]]), np.vstack([rd, rd[dup_r]])
    perm_l, perm_r = rng.permutation(len(left)), rng.permutation(len(right))
    if dtype == np.float32:  # non-integer descriptors
        return (
            left[perm_l],
            (ld[perm_l] + rng.uniform(0, 1, ld.shape)).astype(dtype),
            right[perm_r],
            (rd[perm_r] + rng.uniform(0, 1, rd.shape)).astype(dtype),
        )
    return left[perm_l], ld[perm_l].astype(dtype), right[perm_r], rd[perm_r].astype(dtype)


CONFIGS = {
    "default": MATCH,
    "no left-right check": dataclasses.replace(MATCH, left_right_check=False),
    "loose": dataclasses.replace(MATCH, dist_ratio=0.9, vertical_tolerance_px=4.0, z_min_m=3.0),
}


@pytest.mark.parametrize("cfg_name", list(CONFIGS))
@pytest.mark.parametrize("rig_name", list(RIGS))
def test_matches_equal_the_reference_on_random_scenes(rig_name: str, cfg_name: str):
    rig, cfg = RIGS[rig_name], CONFIGS[cfg_name]
    tied = 0
    for seed in range(3):
        left, ld, right, rd = _random_scene(rig, 10 + seed)
        got = match_stereo(left, ld, right, rd, rig, cfg)
        _assert_same_matches(got, _reference_match(left, ld, right, rd, rig, cfg))
        assert len(got) > 50
        # duplicated left keypoints tie for their right keypoint: the first left index wins
        _, first, group = np.unique(
            np.column_stack([left, ld]), axis=0, return_index=True, return_inverse=True
        )
        matched_twins = group[got.left][
            np.bincount(group, minlength=len(first))[group[got.left]] == 2
        ]
        if cfg.left_right_check:
            assert len(np.unique(matched_twins)) == len(matched_twins)
            assert np.all(np.isin(got.left[np.isin(group[got.left], matched_twins)], first))
        tied += len(matched_twins)
    assert tied > 0


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_matches_equal_the_reference_with_few_windows_and_float_descriptors(rig_name: str):
    rig = RIGS[rig_name]
    # a handful of keypoints: fewer than 8 windows with two candidates, so a lone candidate's
    # D2 comes from the spread-out unrelated pairs
    left, ld, right, rd = _random_scene(rig, 20, n_true=12, n_other=3, n_dup=1)
    got = match_stereo(left, ld, right, rd, rig, MATCH)
    _assert_same_matches(got, _reference_match(left, ld, right, rd, rig, MATCH))
    assert got.candidates_examined > len(left) and np.any(got.ratio == 0)
    # float descriptors (not integer-valued)
    left, ld, right, rd = _random_scene(rig, 21, dtype=np.float32)
    got = match_stereo(left, ld, right, rd, rig, MATCH)
    _assert_same_matches(got, _reference_match(left, ld, right, rd, rig, MATCH), exact=False)
    assert len(got) > 50


def test_quantile_is_numpys_bit_for_bit():
    rng = np.random.default_rng(5)
    for size in [*range(1, 40), 100, 257, 1000]:
        values = (rng.gamma(4.0, 80.0, size) * rng.choice([1.0, 1e-3, 1e3])).astype(np.float32)
        for q in (0.0, 0.1, 0.25, 0.5, 0.75, 1.0):
            want = float(np.quantile(values, q))
            assert _quantile_f32(values.copy(), q) == want, (size, q)


# -- rendered stereo pairs with known correspondences ---------------------------------------


@dataclass
class Pair:
    rig: StereoRig
    left: Keypoints
    right: Keypoints
    depth_left_m: np.ndarray


@pytest.fixture(scope="module")
def terrain() -> Terrain:
    spec = TerrainSpec(
        size_m=(300.0, 300.0),
        origin_nav_m=(-150.0, -150.0),
        relief_m=30.0,
        relief_scale_m=100.0,
        region_scale_m=120.0,
    )
    return make_terrain(spec, np.random.default_rng(3))


@pytest.fixture(scope="module")
def rendered_pairs(terrain: Terrain) -> dict[str, list[Pair]]:
    """Two nadir views (70-80 m above ground, urban and smooth parts) per rig, 8-bit with
    sensor noise."""
    rng = np.random.default_rng(4)
    views = [(0.0, 0.0, 80.0, (2.0, -3.0, 20.0)), (-40.0, 50.0, 70.0, (-4.0, 2.0, -60.0))]
    out: dict[str, list[Pair]] = {}
    for name, rig in RIGS.items():
        rays_l, rays_r = pixel_rays(rig.left), pixel_rays(rig.right)
        pairs = []
        for n, e, agl_m, rpy_deg in views:
            C_nav_body = euler_zyx_to_matrix(*np.radians(rpy_deg))
            z = -(float(terrain.elevation_at(n, e)) + agl_m)
            T_nav_left = make_T(C_nav_body @ R_BODY_CAM, np.array([n, e, z]))
            T_nav_right = T_nav_left @ rig.T_left_right
            vl = render_terrain_view(terrain, rig.left, T_nav_left, rays=rays_l)
            vr = render_terrain_view(terrain, rig.right, T_nav_right, rays=rays_r)
            images = [
                photometric(v.radiance, gain=1.0, offset=0.0, noise_sigma=1.0, rng=rng)
                for v in (vl, vr)
            ]
            kl, _ = detect_and_describe(images[0], SIFT, ADAPTIVE)
            kr, _ = detect_and_describe(images[1], SIFT, ADAPTIVE)
            pairs.append(Pair(rig, kl, kr, vl.depth_m))
        out[name] = pairs
    return out


def _true_right_px(pair: Pair) -> np.ndarray:
    """Raw right pixel of every left keypoint, through its true depth."""
    uv = pair.left.uv_raw_px.astype(np.float32)
    depth = cv2.remap(pair.depth_left_m, uv[:, :1], uv[:, 1:], cv2.INTER_LINEAR).ravel()
    xy = undistort_pixels(pair.rig.left, pair.left.uv_raw_px)
    p_left = np.column_stack([xy, np.ones(len(xy))]) * depth[:, None]
    uv_r, _ = project_points(pair.rig.right, _to_right(pair.rig, p_left))
    return uv_r


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_precision_on_rendered_pairs(rendered_pairs, rig_name: str):
    n_correct = n_matches = n_matchable = 0
    for i, pair in enumerate(rendered_pairs[rig_name]):
        ul = undistort_keypoints(pair.rig.left, pair.left.uv_raw_px)
        ur = undistort_keypoints(pair.rig.right, pair.right.uv_raw_px)
        m = match_stereo(ul, pair.left.desc, ur, pair.right.desc, pair.rig, MATCH)
        truth = _true_right_px(pair)
        err = np.linalg.norm(truth[m.left] - pair.right.uv_raw_px[m.right], axis=1)
        correct = int(np.sum(err < 2.0))
        # left keypoints whose true correspondent was detected in the right image
        d = np.linalg.norm(truth[:, None, :] - pair.right.uv_raw_px[None, :, :], axis=2)
        matchable = int(np.sum(np.nanmin(d, axis=1) < 2.0))
        bf = match_brute_force(pair.left.desc, pair.right.desc, MATCH.dist_ratio)
        bf_err = np.linalg.norm(truth[bf.left] - pair.right.uv_raw_px[bf.right], axis=1)
        print(
            f"{rig_name} view {i}: {len(pair.left)}/{len(pair.right)} keypoints, {len(m)} "
            f"matches, precision {correct / len(m):.3f}, recall {correct / matchable:.3f} "
            f"({matchable} matchable), {m.candidates_per_keypoint:.2f} candidates per left "
            f"keypoint ({100 * m.candidates_per_keypoint / len(pair.right):.2f}% of the right "
            f"keypoints); brute force: {len(bf)} matches, precision {np.mean(bf_err < 2):.3f}"
        )
        assert m.candidates_per_keypoint <= 0.03 * len(pair.right)
        assert correct >= 0.8 * matchable
        n_correct, n_matches, n_matchable = (
            n_correct + correct,
            n_matches + len(m),
            n_matchable + matchable,
        )
    assert n_correct / n_matches >= 0.98


@pytest.mark.parametrize("rig_name", list(RIGS))
def test_matches_equal_the_reference_on_rendered_pairs(rendered_pairs, rig_name: str):
    for pair in rendered_pairs[rig_name]:
        ul = undistort_keypoints(pair.rig.left, pair.left.uv_raw_px)
        ur = undistort_keypoints(pair.rig.right, pair.right.uv_raw_px)
        got = match_stereo(ul, pair.left.desc, ur, pair.right.desc, pair.rig, MATCH)
        want = _reference_match(ul, pair.left.desc, ur, pair.right.desc, pair.rig, MATCH)
        _assert_same_matches(got, want)
        assert len(got) > 50


def test_brute_force_examines_every_pair(rendered_pairs):
    pair = rendered_pairs["rectified"][0]
    bf = match_brute_force(pair.left.desc, pair.right.desc, MATCH.dist_ratio)
    assert bf.candidates_examined == len(pair.left) * len(pair.right)
    assert np.all(np.isnan(bf.disparity_px)) and np.all(bf.ratio < MATCH.dist_ratio)
    assert isinstance(bf, StereoMatches) and len(bf) > 50


# -- real data -----------------------------------------------------------------------------


def _read_rig_euroc(mav0: Path) -> StereoRig:
    import yaml

    cams = []
    for name in ("cam0", "cam1"):
        text = (mav0 / name / "sensor.yaml").read_text()
        data = yaml.safe_load(text.split("\n", 1)[1] if text.startswith("%YAML") else text)
        fu, fv, cu, cv = data["intrinsics"]
        k1, k2, p1, p2 = data["distortion_coefficients"]
        cams.append(
            CameraModel(
                width=int(data["resolution"][0]),
                height=int(data["resolution"][1]),
                K=np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]]),
                D=np.array([k1, k2, p1, p2, 0.0]),
                distortion_model="plumb_bob",
                T_body_cam=np.array(data["T_BS"]["data"], float).reshape(4, 4),
            )
        )
    return StereoRig(cams[0], cams[1])


def _read_rig_kitti(clip: Path, width: int, height: int) -> StereoRig:
    rows = [line.split() for line in (clip / "calib.txt").read_text().splitlines() if line.strip()]
    P0, P1 = (np.array([float(v) for v in r[-12:]]).reshape(3, 4) for r in rows[:2])
    b_m = -P1[0, 3] / P1[0, 0]
    return StereoRig(
        CameraModel(width, height, P0[:, :3].copy(), P=P0),
        CameraModel(
            width,
            height,
            P1[:, :3].copy(),
            P=P1,
            T_body_cam=make_T(np.eye(3), np.array([b_m, 0, 0])),
        ),
    )


def _frames(left_dir: Path, right_dir: Path) -> list[tuple[Path, Path]]:
    left = sorted(left_dir.glob("*.png"))
    if not left:
        pytest.skip(f"{left_dir} holds no images")
    picks = [left[i] for i in (0, len(left) // 2, len(left) - 1)]
    return [(p, right_dir / p.name) for p in picks]


@pytest.mark.realdata
@pytest.mark.parametrize(
    ("dataset", "depth_range_m", "min_within_1px"),
    # KITTI: SIFT localisation on these clips scatters v_l - v_r by ~0.6 px (std, after
    # removing a 0.05 degree residual rotation of the rectification), so fewer pairs fall
    # within 1 px than on EuRoC; all lie within the 1.5 px band.
    [("euroc", (1.0, 10.0), 0.93), ("kitti", (3.0, 80.0), 0.75)],
)
def test_real_pairs_are_epipolar_and_at_plausible_depths(
    shared_data: Path, dataset: str, depth_range_m: tuple[float, float], min_within_1px: float
):
    if dataset == "euroc":
        mav0 = shared_data / "euroc_v101_micro" / "mav0"
        if not (mav0 / "cam1" / "sensor.yaml").is_file():
            pytest.skip(f"{mav0} not found")
        rig = _read_rig_euroc(mav0)
        frames = _frames(mav0 / "cam0" / "data", mav0 / "cam1" / "data")
    else:
        clip = shared_data / "kitti_clip_a"
        if not (clip / "calib.txt").is_file():
            pytest.skip(f"{clip} not found")
        frames = _frames(clip / "image_l", clip / "image_r")
        h, w = cv2.imread(str(frames[0][0]), cv2.IMREAD_GRAYSCALE).shape
        rig = _read_rig_kitti(clip, w, h)
    assert rig.rectified == (dataset == "kitti")
    M_left, M_right = projection_matrices(rig)
    for left_path, right_path in frames:
        kl, _ = detect_and_describe(
            cv2.imread(str(left_path), cv2.IMREAD_GRAYSCALE), SIFT, ADAPTIVE
        )
        kr, _ = detect_and_describe(
            cv2.imread(str(right_path), cv2.IMREAD_GRAYSCALE), SIFT, ADAPTIVE
        )
        ul = undistort_keypoints(rig.left, kl.uv_raw_px)
        ur = undistort_keypoints(rig.right, kr.uv_raw_px)
        t0 = time.perf_counter()
        m = match_stereo(ul, kl.desc, ur, kr.desc, rig, MATCH)
        t1 = time.perf_counter()
        bf = match_brute_force(kl.desc, kr.desc, MATCH.dist_ratio)
        t2 = time.perf_counter()
        residual = epipolar_residual_px(rig, ul[m.left], ur[m.right])
        depth = triangulate(M_left, M_right, ul[m.left], ur[m.right])[:, 2]
        lo, hi = depth_range_m
        print(
            f"{dataset} {left_path.name}: {len(kl)}/{len(kr)} keypoints, {len(m)} matches, "
            f"{m.candidates_per_keypoint:.2f} candidates per keypoint, residual < 1 px "
            f"{np.mean(residual < 1):.3f}, depth in [{lo:g}, {hi:g}] m "
            f"{np.mean((depth >= lo) & (depth <= hi)):.3f}, 5/50/95% "
            f"{np.percentile(depth, [5, 50, 95]).round(1).tolist()} m, "
            f"{1e3 * (t1 - t0):.1f} ms (brute force {len(bf)} matches, {1e3 * (t2 - t1):.1f} ms)"
        )
        assert len(m) >= 100
        assert np.mean(residual < 1.0) >= min_within_1px
        assert residual.max() <= MATCH.vertical_tolerance_px + 0.5
        assert m.candidates_per_keypoint <= 0.03 * len(kr)
        # points near infinity may triangulate behind the rig (disparity within the band's
        # slack below zero); nearly all lie in front, most at the scene's depths
        assert np.mean(depth > 0) >= 0.98
        assert np.mean((depth >= lo) & (depth <= hi)) >= 0.85
        if dataset == "kitti":  # rectified: disparity >= 0 up to the band's slack
            assert m.disparity_px.min() >= -MATCH.vertical_tolerance_px
