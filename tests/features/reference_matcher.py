"""Plain matchers for the tests and benchmarks.

`match_reference` is the readable specification of `cvslam_cli.features.matching.match_stereo`:
the search window of eq. 20-34 and the ratio test written as the paper states them, over all
(left, right) pairs, with no speed tricks; the tests require `match_stereo` to return the same
matches. `match_brute_force` is the plain approach of the benchmarks: every left descriptor
against all right ones (OpenCV's brute-force matcher), no geometry.
"""

from __future__ import annotations

import cv2
import numpy as np

from cvslam_cli.config import StereoMatchConfig
from cvslam_cli.features.matching import LONE_D2_QUANTILE, MIN_WINDOWS_FOR_TYPICAL_D2, StereoMatches
from cvslam_cli.features.windows import auto_z_min_m
from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.geometry.rotations import invert_T


def _right_from_left(rig: StereoRig) -> tuple[np.ndarray, np.ndarray]:
    T_rl = invert_T(rig.T_left_right)
    return T_rl[:3, :3], T_rl[:3, 3]


def fundamental_matrix(rig: StereoRig) -> np.ndarray:
    """(3, 3) F with x_r^T F x_l = 0 for ideal pixels (eq. 24-25): K_r^-T [t_rl]x R_rl K_l^-1."""
    R, t = _right_from_left(rig)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(rig.right.K).T @ tx @ R @ np.linalg.inv(rig.left.K)


def epipolar_residual_px(rig: StereoRig, left_uv_px: np.ndarray, right_uv_px: np.ndarray):
    """(N,) distance (ideal right pixels) of each right point to the epipolar line of its left
    point (eq. 27: v_r = A u_r + B)."""
    xl = np.column_stack([np.asarray(left_uv_px, float).reshape(-1, 2), np.ones(len(left_uv_px))])
    xr = np.column_stack([np.asarray(right_uv_px, float).reshape(-1, 2), np.ones(len(right_uv_px))])
    lines = xl @ fundamental_matrix(rig).T  # (a, b, c): a u + b v + c = 0 in the right image
    return np.abs(np.einsum("ij,ij->i", lines, xr)) / np.hypot(lines[:, 0], lines[:, 1])


def in_window(
    rig: StereoRig, z_min_m: float, tolerance_px: float, left_uv: np.ndarray, right_uv: np.ndarray
) -> np.ndarray:
    """(N, M) whether right point j (ideal pixels) lies in the search window of left point i
    (eq. 20-34): the right image of the left ray's points from depth z_min (HD_max = f b /
    z_min for a rectified pair, eq. 23) to infinity (zero disparity) is a segment of the
    epipolar line of F (eq. 24-29); the window holds the points within `tolerance_px` (VD_max,
    eq. 34) of that line and at most `tolerance_px` beyond either end of the segment. Rays
    whose far points lie behind the right camera have no window; depths that would put a
    point behind the right camera are not searched. (Not covered: a left point at the
    epipole, whose segment has no direction.)"""
    R, t = _right_from_left(rig)
    K_r = rig.right.K
    n = len(left_uv)
    rays = np.column_stack([left_uv, np.ones(n)]) @ np.linalg.inv(rig.left.K).T  # depth 1
    ahead = rays @ R.T  # the rays' directions in the right camera frame
    has_window = ahead[:, 2] > 1e-12
    far = ahead @ K_r.T
    far = far[:, :2] / far[:, 2:]  # the image of the point at infinity
    z_near = np.maximum(z_min_m, (1e-6 - t[2]) / np.maximum(ahead[:, 2], 1e-12))
    near = (z_near[:, None] * ahead + t) @ K_r.T
    near = near[:, :2] / near[:, 2:]  # the image of the point at the nearest depth searched
    length = np.linalg.norm(near - far, axis=1)
    along_dir = (near - far) / length[:, None]
    lines = np.column_stack([left_uv, np.ones(n)]) @ fundamental_matrix(rig).T
    lines /= np.hypot(lines[:, 0], lines[:, 1])[:, None]  # a u + b v + c = signed distance
    rel = right_uv[None, :, :] - far[:, None, :]  # (N, M, 2)
    along = np.einsum("nmk,nk->nm", rel, along_dir)
    across = np.abs(right_uv @ lines[:, :2].T + lines[:, 2]).T
    return (
        has_window[:, None]
        & (across <= tolerance_px)
        & (along >= -tolerance_px)
        & (along <= length[:, None] + tolerance_px)
    )


def _distances(ld: np.ndarray, rd: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """D(i, j) = |d_i - d_j|_2 in float64, rounded once to float32 (for integer descriptors
    the square root of an exact integer: what float32 arithmetic gives too)."""
    diff = ld[i].astype(np.float64) - rd[j].astype(np.float64)
    return np.sqrt((diff**2).sum(axis=1)).astype(np.float32)


def match_reference(
    luv: np.ndarray,
    ld: np.ndarray,
    ruv: np.ndarray,
    rd: np.ndarray,
    rig: StereoRig,
    cfg: StereoMatchConfig,
) -> StereoMatches:
    """`match_stereo`'s rules written plainly. Candidates: every (left, right) pair in the
    window (`in_window`). Per left keypoint: D1, D2 the smallest and second smallest
    candidate distances; a lone candidate's D2 is the lower quartile of the other windows'
    D2 (of the distances of 64 spread-out pairs when fewer than 8 windows have two
    candidates); accepted if D1 < DistRatio * D2 (in float32). Left-right check: the right
    keypoint's nearest left keypoint among all its candidates (equal distances: the smaller
    left index) must be this one. (Which of two equally near right keypoints is D1's does
    not matter: then D2 = D1 and the ratio test rejects the match.)"""
    n, m = len(luv), len(ruv)
    if n == 0 or m == 0:
        return StereoMatches.empty(n, m)
    inside = in_window(rig, auto_z_min_m(rig, cfg.z_min_m), cfg.vertical_tolerance_px, luv, ruv)
    li, rj = inside.nonzero()
    if len(li) == 0:
        return StereoMatches.empty(n, m)
    dist = _distances(ld, rd, li, rj)
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
        unrelated = _distances(ld, rd, (i * n) // k, (i * 7919 + m // 2) % m)
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


def match_brute_force(
    left_desc: np.ndarray, right_desc: np.ndarray, dist_ratio: float
) -> StereoMatches:
    """The plain approach, for benchmarks: every left descriptor against ALL right ones
    (cv2.BFMatcher, k = 2 nearest) and the ratio test. No geometry, so `disparity_px` is
    NaN."""
    ld = np.asarray(left_desc, dtype=np.float32)
    rd = np.asarray(right_desc, dtype=np.float32)
    n, m = ld.shape[0], rd.shape[0]
    if n == 0 or m == 0:
        return StereoMatches.empty(n, m)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(ld, rd, k=2)
    left, right, dist, ratio = [], [], [], []
    for pair in knn:
        if not pair:
            continue
        best = pair[0]
        if len(pair) < 2:
            left.append(best.queryIdx)
            right.append(best.trainIdx)
            dist.append(best.distance)
            ratio.append(0.0)
        elif best.distance < dist_ratio * pair[1].distance:
            left.append(best.queryIdx)
            right.append(best.trainIdx)
            dist.append(best.distance)
            ratio.append(best.distance / pair[1].distance if pair[1].distance > 0 else 0.0)
    k = len(left)
    return StereoMatches(
        left=np.asarray(left, np.int64),
        right=np.asarray(right, np.int64),
        disparity_px=np.full(k, np.nan, np.float32),
        distance=np.asarray(dist, np.float32),
        ratio=np.asarray(ratio, np.float32),
        candidates_examined=n * m,
        n_left=n,
        n_right=m,
    )
