"""Stereo-constrained matching of SIFT keypoints (paper, "Stereo vision constraints" and
"Disparity analysis", eq. 20-34).

Descriptor distance (unnumbered, before eq. 20): D(i, j) = |d_i - d_j|_2. A left keypoint i is
matched to the right keypoint k of smallest distance D1 if D1 < DistRatio * D2, D2 being the
second smallest. Instead of comparing i with all M right keypoints (M x 128 operations per
left keypoint), the paper compares it only with the right keypoints inside a window:
horizontal disparity up to HD_max = f b / z_min (eq. 20-23: z = f b / d, nothing is nearer
than z_min) and vertical distance up to VD_max = |A| HD_max from the epipolar line
v_r = A u_r + B of the fundamental matrix (eq. 24-29: p_r^T F p_l = 0; eq. 30-34: the window;
a pixel or two once rectified). The paper centres the window on u_l (eq. 30, half-width
HD_max / 2); the sign of the disparity being known, the window here runs from zero disparity
to HD_max.

One mechanism for rectified and unrectified rigs. All coordinates are *ideal* pixels (lens
distortion removed, each camera's own K; `undistort_keypoints`). The point at depth z on the
ray of left pixel x_l projects into the right image at

    x_r(z) ~ z H_inf x_l + K_r t_rl,      H_inf = K_r R_rl K_l^-1,

(R_rl, t_rl: left camera frame -> right camera frame), a straight segment as z runs from z_min
to infinity: from x_r(z_min) to the image of the ray's point at infinity, H_inf x_l. This is
the epipolar line of x_l (F = K_r^-T [t_rl]x R_rl K_l^-1) cut to the depths that can occur. For
a rectified pair H_inf = I and the segment is the row of x_l from disparity 0 to
HD_max = f b / z_min. The window is that segment widened by `vertical_tolerance_px` (VD_max)
across the line and by the same amount beyond both ends.

The candidate search is vectorised: right keypoints are sorted by their coordinate across the
dominant epipolar direction (v for side-by-side rigs), each window's bounding range found by
`np.searchsorted`, the (left, right) pairs expanded with repeat/cumsum, then filtered exactly
against the window; descriptor distances are computed for the surviving pairs only.
`left_right_check` then keeps a match only if its left keypoint is also the best among the
candidates of its right keypoint.

Lone candidates (an addition to the paper). A window holding a single right keypoint has no
second-best distance, and accepting its candidate unconditionally lets any unlike keypoint
through when the true match was not detected: on rendered stereo pairs most wrong matches were
such lone candidates, with distances typical of unrelated descriptors. A wrong lone candidate
is one draw from the distribution of distances to unrelated keypoints, which the second-best
distances D2 of the windows with two or more candidates sample; the lone candidate's D2 is the
lower quartile of those (of 64 spread-out (left, right) pairs, counted in
`candidates_examined`, when fewer than 8 such windows exist), so it passes the ratio test only
when clearly nearer than most unrelated keypoints. Measured on 16 rendered pairs (8 rectified,
8 unrectified): accepting lone candidates unconditionally, precision 0.977 / 0.976; against
the median D2, 0.987 / 0.985; against the lower quartile, 0.992 / 0.989 at the same recall
(0.92 / 0.87); rejecting them, 0.992 / 0.990 but recall 0.51 / 0.41. Their `ratio` is
reported as 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.config import StereoMatchConfig
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.projection import undistort_pixels
from cvslam_cli.geometry.rotations import invert_T

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
U8 = NDArray[np.uint8]
BOOL = NDArray[np.bool_]

AUTO_Z_MIN_BASELINES = 4.0
"""`z_min_m: 0` means max(AUTO_Z_MIN_FLOOR_M, AUTO_Z_MIN_BASELINES * baseline)."""
AUTO_Z_MIN_FLOOR_M = 0.5
MIN_WINDOWS_FOR_TYPICAL_D2 = 8
"""Windows with >= 2 candidates needed to take the typical D2 from them (else random pairs)."""
LONE_D2_QUANTILE = 0.25
"""A lone candidate's D2: this quantile of the second-best distances of the other windows."""


def undistort_keypoints(cam: CameraModel, uv_raw_px: NDArray[np.floating]) -> F64:
    """(N, 2) raw pixel coordinates -> (N, 2) ideal pinhole pixels of the camera's own K
    (u = fx x + s y + cx, v = fy y + cy with (x, y) the undistorted normalised coordinates)."""
    uv = np.asarray(uv_raw_px, dtype=float).reshape(-1, 2)
    if uv.shape[0] == 0:
        return np.zeros((0, 2))
    if not cam.has_distortion or cam.distortion_model == "none":
        return uv.copy()
    xy = undistort_pixels(cam, uv)
    K = cam.K
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1)


def auto_z_min_m(rig: StereoRig, z_min_m: float = 0.0) -> float:
    """The nearest depth searched: `z_min_m`, or when 0 max(0.5 m, 4 baselines)."""
    if z_min_m > 0:
        return float(z_min_m)
    return max(AUTO_Z_MIN_FLOOR_M, AUTO_Z_MIN_BASELINES * rig.baseline_m)


def _right_from_left(rig: StereoRig) -> tuple[F64, F64]:
    """(R_rl, t_rl): left camera coordinates -> right camera coordinates."""
    T_rl = invert_T(rig.T_left_right)
    return T_rl[:3, :3], T_rl[:3, 3]


def fundamental_matrix(rig: StereoRig) -> F64:
    """(3, 3) F with x_r^T F x_l = 0 for ideal pixels (eq. 24-25): K_r^-T [t_rl]x R_rl K_l^-1."""
    R, t = _right_from_left(rig)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(rig.right.K).T @ tx @ R @ np.linalg.inv(rig.left.K)


def epipolar_residual_px(
    rig: StereoRig, left_uv_px: NDArray[np.floating], right_uv_px: NDArray[np.floating]
) -> F64:
    """(N,) distance (ideal right pixels) of each right point to the epipolar line of its left
    point (eq. 27: v_r = A u_r + B)."""
    xl = np.column_stack([np.asarray(left_uv_px, float).reshape(-1, 2), np.ones(len(left_uv_px))])
    xr = np.column_stack([np.asarray(right_uv_px, float).reshape(-1, 2), np.ones(len(right_uv_px))])
    lines = xl @ fundamental_matrix(rig).T  # (a, b, c): a u + b v + c = 0 in the right image
    return np.abs(np.einsum("ij,ij->i", lines, xr)) / np.hypot(lines[:, 0], lines[:, 1])


@dataclass(frozen=True, eq=False)
class SearchWindow:
    """Where the right-image match of each of N left keypoints may lie (ideal right pixels).

    start_px: (N, 2) image of the left ray's point at infinity (zero disparity).
    direction: (N, 2) unit vector along the epipolar line from `start_px` towards nearer
        depths. length_px: (N,) segment length to the image of the point at z_min (for a
        rectified pair HD_max = f b / z_min, eq. 23).
    valid: (N,) the ray has points beyond z_min in front of the right camera.
    tolerance_px: half-width of the band around the segment, and slack beyond its ends
        (VD_max, eq. 34).
    """

    start_px: F64
    direction: F64
    length_px: F64
    valid: BOOL
    tolerance_px: float

    def __len__(self) -> int:
        return int(self.start_px.shape[0])

    def bounds(self) -> tuple[F64, F64]:
        """((N, 2) lower, (N, 2) upper) corners of each window's bounding box."""
        d, tol = self.direction, self.tolerance_px
        p0 = self.start_px - tol * d
        p1 = self.start_px + (self.length_px + tol)[:, None] * d
        half = tol * np.abs(d[:, ::-1])  # the normal (-d_y, d_x), in absolute value
        return np.minimum(p0, p1) - half, np.maximum(p0, p1) + half

    def contains(self, left_idx: I64, right_uv_px: F64) -> BOOL:
        """Whether right point k lies in the window of left keypoint `left_idx[k]`."""
        rel = right_uv_px - self.start_px[left_idx]
        d = self.direction[left_idx]
        along = rel[:, 0] * d[:, 0] + rel[:, 1] * d[:, 1]
        across = rel[:, 0] * d[:, 1] - rel[:, 1] * d[:, 0]
        tol = self.tolerance_px
        return (
            self.valid[left_idx]
            & (np.abs(across) <= tol)
            & (along >= -tol)
            & (along <= self.length_px[left_idx] + tol)
        )


def search_windows(
    left_uv_px: NDArray[np.floating], rig: StereoRig, z_min_m: float, tolerance_px: float
) -> SearchWindow:
    """The `SearchWindow` of each left keypoint (ideal left pixels), for depths >= z_min_m."""
    uv = np.asarray(left_uv_px, dtype=float).reshape(-1, 2)
    n = uv.shape[0]
    R, t = _right_from_left(rig)
    H_inf = rig.right.K @ R @ np.linalg.inv(rig.left.K)
    a = np.column_stack([uv, np.ones(n)]) @ H_inf.T  # x_r(z) ~ z a + e
    e = rig.right.K @ t
    valid = a[:, 2] > 1e-12  # far points of the ray lie in front of the right camera
    a2 = np.where(valid, a[:, 2], 1.0)
    start = a[:, :2] / a2[:, None]
    # nearest depth searched, pushed beyond the right camera's focal plane where needed
    z_near = np.maximum(z_min_m, (1e-6 - e[2]) / a2)
    w_near = z_near * a2 + e[2]
    near = (z_near[:, None] * a[:, :2] + e[:2]) / w_near[:, None]
    seg = near - start
    length = np.hypot(seg[:, 0], seg[:, 1])
    ok = length > 1e-9
    direction = np.where(
        ok[:, None], seg / np.where(ok, length, 1.0)[:, None], np.array([-1.0, 0.0])
    )
    length = np.where(ok, length, 0.0)
    valid &= np.all(np.isfinite(start), axis=1) & np.isfinite(length)
    return SearchWindow(start, direction, length, valid, float(tolerance_px))


@dataclass(frozen=True, eq=False)
class StereoMatches:
    """Matches between N_left and N_right keypoints of one stereo pair (M of them), sorted by
    left index.

    left, right: (M,) int64 indices into the left and right keypoint arrays.
    disparity_px: (M,) float32 u_l - u_r in ideal pixels (NaN from `match_brute_force`,
        which has no coordinates).
    distance: (M,) float32 descriptor distance D1 of the match.
    ratio: (M,) float32 D1 / D2, 0 when the window held a single candidate.
    candidates_examined: (left, right) pairs whose descriptors were compared.
    """

    left: I64
    right: I64
    disparity_px: F32
    distance: F32
    ratio: F32
    candidates_examined: int
    n_left: int
    n_right: int

    def __len__(self) -> int:
        return int(self.left.shape[0])

    @property
    def candidates_per_keypoint(self) -> float:
        return self.candidates_examined / self.n_left if self.n_left else 0.0

    @staticmethod
    def empty(n_left: int, n_right: int, candidates_examined: int = 0) -> StereoMatches:
        i = np.zeros(0, np.int64)
        f = np.zeros(0, np.float32)
        return StereoMatches(
            i, i.copy(), f, f.copy(), f.copy(), candidates_examined, n_left, n_right
        )


def _as_points(uv: NDArray[np.floating], side: str) -> F64:
    pts = np.asarray(uv, dtype=float)
    if pts.size == 0:
        return np.zeros((0, 2))
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"{side} keypoints: expected (N, 2) coordinates, got shape {pts.shape}")
    return pts


def _as_descriptors(desc: np.ndarray, n: int, side: str) -> np.ndarray:
    d = np.asarray(desc)
    if d.size == 0 and n == 0:
        return np.zeros((0, d.shape[1] if d.ndim == 2 else 128), d.dtype)
    if d.ndim != 2 or d.shape[0] != n:
        raise ValueError(f"{side} descriptors: expected ({n}, D) for {n} keypoints, got {d.shape}")
    return d


def candidate_pairs(window: SearchWindow, right_uv_px: F64) -> tuple[I64, I64]:
    """(left, right) index pairs of every right keypoint inside every left window, sorted by
    left index (vectorised: sort + searchsorted + repeat, then the exact window test)."""
    n, m = len(window), int(right_uv_px.shape[0])
    if n == 0 or m == 0 or not window.valid.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d = window.direction[window.valid]
    # sort across the dominant epipolar direction: v for horizontal lines, u for vertical
    axis = 1 if np.abs(d[:, 0]).sum() >= np.abs(d[:, 1]).sum() else 0
    order = np.argsort(right_uv_px[:, axis], kind="stable")
    coord = right_uv_px[order, axis]
    lo_box, hi_box = window.bounds()
    lo = np.searchsorted(coord, lo_box[:, axis], side="left")
    hi = np.searchsorted(coord, hi_box[:, axis], side="right")
    counts = np.where(window.valid, np.maximum(hi - lo, 0), 0)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    left_idx = np.repeat(np.arange(n, dtype=np.int64), counts)
    first = np.cumsum(counts) - counts
    pos = np.arange(total, dtype=np.int64) - np.repeat(first, counts) + np.repeat(lo, counts)
    right_idx = order[pos].astype(np.int64)
    keep = window.contains(left_idx, right_uv_px[right_idx])
    return left_idx[keep], right_idx[keep]


def _descriptor_distances(left_desc: np.ndarray, right_desc: np.ndarray, li: I64, rj: I64) -> F32:
    """Euclidean descriptor distances of the listed pairs. SIFT descriptors are integers <= 255,
    so the float32 squared sums (< 2^24) are exact."""
    out = np.empty(li.shape[0], np.float32)
    chunk = 65536
    for s in range(0, li.shape[0], chunk):
        a = left_desc[li[s : s + chunk]].astype(np.float32)
        a -= right_desc[rj[s : s + chunk]]
        out[s : s + chunk] = np.einsum("ij,ij->i", a, a)
    return np.sqrt(out, out=out)


def _unrelated_pairs(n: int, m: int, count: int = 64) -> tuple[I64, I64]:
    """Up to `count` (left, right) pairs spread over both keypoint lists, with unrelated
    positions (a stride coprime to most list lengths), to estimate the distance between
    descriptors of different points."""
    k = min(count, n * m)
    i = np.arange(k, dtype=np.int64)
    return (i * n) // k, (i * 7919 + m // 2) % m


def _best_two(group: I64, dist: F32, n_groups: int) -> tuple[I64, F32, F32, I64]:
    """Per group (pairs sorted by group): (index of the best pair or -1, D1, D2 (inf if
    none), number of candidates)."""
    order = np.lexsort((dist, group))
    g = group[order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    counts = np.diff(np.r_[starts, g.shape[0]])
    best = np.full(n_groups, -1, np.int64)
    d1 = np.full(n_groups, np.inf, np.float32)
    d2 = np.full(n_groups, np.inf, np.float32)
    n_cand = np.zeros(n_groups, np.int64)
    gid = g[starts]
    best[gid] = order[starts]
    d1[gid] = dist[order[starts]]
    two = counts >= 2
    d2[gid[two]] = dist[order[starts[two] + 1]]
    n_cand[gid] = counts
    return best, d1, d2, n_cand


def match_stereo(
    left_uv_px: NDArray[np.floating],
    left_desc: np.ndarray,
    right_uv_px: NDArray[np.floating],
    right_desc: np.ndarray,
    rig: StereoRig,
    cfg: StereoMatchConfig,
) -> StereoMatches:
    """Match left to right keypoints (ideal pixels, `undistort_keypoints`) inside their
    stereo search windows (eq. 20-34), with the ratio test and, if
    `cfg.left_right_check`, mutual consistency."""
    luv, ruv = _as_points(left_uv_px, "left"), _as_points(right_uv_px, "right")
    n, m = luv.shape[0], ruv.shape[0]
    ld, rd = _as_descriptors(left_desc, n, "left"), _as_descriptors(right_desc, m, "right")
    if ld.shape[1] != rd.shape[1]:
        raise ValueError(f"descriptor sizes differ: left {ld.shape[1]}, right {rd.shape[1]}")
    if n == 0 or m == 0:
        return StereoMatches.empty(n, m)
    window = search_windows(luv, rig, auto_z_min_m(rig, cfg.z_min_m), cfg.vertical_tolerance_px)
    li, rj = candidate_pairs(window, ruv)
    if li.shape[0] == 0:
        return StereoMatches.empty(n, m)
    dist = _descriptor_distances(ld, rd, li, rj)
    examined = int(li.shape[0])

    best, d1, d2, n_cand = _best_two(li, dist, n)  # D_min1, D_min2 per left keypoint
    has = best >= 0
    # D1 < DistRatio * D2. A lone candidate has no D2 of its own: it is compared with the
    # typical distance to an unrelated keypoint (module docstring, "Lone candidates")
    lone = n_cand == 1
    if lone.any():
        multi = n_cand >= 2
        if int(multi.sum()) >= MIN_WINDOWS_FOR_TYPICAL_D2:
            d2_typical = float(np.quantile(d2[multi], LONE_D2_QUANTILE))
        else:
            li_r, rj_r = _unrelated_pairs(n, m)
            unrelated = _descriptor_distances(ld, rd, li_r, rj_r)
            d2_typical = float(np.quantile(unrelated, LONE_D2_QUANTILE))
            examined += int(li_r.shape[0])
        d2 = np.where(lone, np.float32(d2_typical), d2)
    accept = has & (d1 < cfg.dist_ratio * d2)
    if cfg.left_right_check:
        best_r, _, _, _ = _best_two(rj, dist, m)  # the best left keypoint of each right one
        pair = np.where(has, best, 0)
        accept &= best_r[rj[pair]] == pair
    sel = np.flatnonzero(accept)
    pair = best[sel]
    right = rj[pair]
    ratio = np.where(lone[sel], 0.0, d1[sel] / np.maximum(d2[sel], np.float32(1e-12)))
    return StereoMatches(
        left=sel.astype(np.int64),
        right=right.astype(np.int64),
        disparity_px=(luv[sel, 0] - ruv[right, 0]).astype(np.float32),
        distance=d1[sel].astype(np.float32),
        ratio=ratio.astype(np.float32),
        candidates_examined=examined,
        n_left=n,
        n_right=m,
    )


def match_brute_force(
    left_desc: np.ndarray, right_desc: np.ndarray, dist_ratio: float
) -> StereoMatches:
    """The plain approach, for benchmarks: every left descriptor against ALL right ones
    (cv2.BFMatcher, k = 2 nearest) and the ratio test. No geometry, so
    `disparity_px` is NaN."""
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
