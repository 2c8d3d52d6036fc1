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

The whole matcher is a fixed sequence of whole-array operations, with no loop over keypoints
(a few hundred keypoints per image make numpy's per-call overhead, not arithmetic, the cost):
all windows at once (`search_windows`, on (2, N) arrays); the right keypoints bucketed by
their coordinate across the dominant epipolar direction (v for side-by-side rigs) with one
sort, each window's range of buckets by one `searchsorted`, all (left, right) pairs gathered
at once and filtered exactly against the windows (`candidate_pairs`); descriptor distances
of the surviving pairs in one batched operation (`_descriptor_distances`); D1, D2 per left
keypoint and the best left keypoint per right one by unbuffered minimum reductions over
64-bit keys (`match_stereo`). `left_right_check` keeps a match only if its left keypoint is
also the best among the candidates of its right keypoint.

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

import math
import sys
import threading
import weakref
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.config import StereoMatchConfig
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.projection import undistort_pixels
from cvslam_cli.geometry.rotations import invert_T
from cvslam_cli.records.arrays import F32, F64, I64, U8, U16

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
    return _z_min(_rig_geometry(rig), z_min_m)


def _right_from_left(rig: StereoRig) -> tuple[F64, F64]:
    """(R_rl, t_rl): left camera coordinates -> right camera coordinates."""
    T_rl = invert_T(rig.T_left_right)
    return T_rl[:3, :3], T_rl[:3, 3]


@dataclass(frozen=True, eq=False)
class _RigGeometry:
    """What the windows need of a rig. H_inf: (3, 3) K_r R_rl K_l^-1 (the infinite homography);
    e: (3,) K_r t_rl (the right epipole, homogeneous); baseline_m. rows_only: the pair is
    rectified (same K, R_rl = I, baseline along x, to rounding): H_inf = I, e = (f b_x, 0, 0),
    and every window is its keypoint's row from zero disparity to HD_max = f b / z_min
    (eq. 23)."""

    H_inf: F64
    e: F64
    baseline_m: float
    rows_only: bool


_RIG_GEOMETRY: weakref.WeakKeyDictionary[StereoRig, _RigGeometry] = weakref.WeakKeyDictionary()


def _rig_geometry(rig: StereoRig) -> _RigGeometry:
    """`_RigGeometry` of a rig, memoised per rig object (rigs are frozen records): two 3x3
    inverses and a few rigid-transform products saved per frame."""
    geo = _RIG_GEOMETRY.get(rig)
    if geo is None:
        R, t = _right_from_left(rig)
        K_l, K_r = rig.left.K, rig.right.K
        rows_only = bool(  # to rounding (1e-9: windows move by ~1e-6 px at most)
            np.allclose(R, np.eye(3), rtol=0.0, atol=1e-9)
            and np.allclose(K_l, K_r, rtol=1e-12, atol=0.0)
            and np.array_equal(K_r[2], [0.0, 0.0, 1.0])
            and abs(t[1]) + abs(t[2]) <= 1e-9 * abs(t[0])
        )
        geo = _RigGeometry(
            H_inf=np.eye(3) if rows_only else K_r @ R @ np.linalg.inv(K_l),
            e=K_r @ t,
            baseline_m=rig.baseline_m,
            rows_only=rows_only,
        )
        _RIG_GEOMETRY[rig] = geo
    return geo


def _z_min(geo: _RigGeometry, z_min_m: float) -> float:
    if z_min_m > 0:
        return float(z_min_m)
    return max(AUTO_Z_MIN_FLOOR_M, AUTO_Z_MIN_BASELINES * geo.baseline_m)


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


_ROWS = 9
"""Rows of a window parameter block: start (2), direction d (2), (d_y, -d_x) (2), length / 2,
length / 2 + tolerance, length. The first `_TESTED` are what the window test reads."""
_TESTED = 8


def _window_rows(start: F64, direction: F64, length_px: F64, tolerance_px: float) -> F64:
    """(9, N) parameter block of N windows from (2, N) start and direction, (N,) length."""
    rows = np.empty((_ROWS, start.shape[1]))
    rows[0:4] = start[0], start[1], direction[0], direction[1]
    rows[4] = direction[1]
    np.negative(direction[0], out=rows[5])
    np.multiply(length_px, 0.5, out=rows[6])
    np.add(rows[6], tolerance_px, out=rows[7])
    rows[8] = length_px
    return rows


def _inside(rows: F64, right: F64, tolerance_px: float) -> BOOL:
    """(K,) whether right point `right[:, k]` ((2, K)) lies in the window whose parameter
    block (`_window_rows`) is `rows[:, k]` (eq. 30-34): within `tolerance_px` of the
    epipolar line, and from `tolerance_px` before the segment's start to `tolerance_px`
    beyond its end (|along - length / 2| <= length / 2 + tolerance)."""
    rel = right - rows[0:2]
    x = rel[0] * rows[2:4]  # (along, across) = (rel . d, rel x d)
    x += rel[1] * rows[4:6]
    x[0] -= rows[6]
    np.abs(x, out=x)
    return (x[0] <= rows[7]) & (x[1] <= tolerance_px)


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
    rows: optional (9, N) parameter block of the same windows (`_window_rows`), which
        `search_windows` fills and the candidate search gathers from.
    """

    start_px: F64
    direction: F64
    length_px: F64
    valid: BOOL
    tolerance_px: float
    rows: F64 | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.start_px.shape[0])

    def parameter_rows(self) -> F64:
        """(9, N) parameter block (`_window_rows`)."""
        if self.rows is not None:
            return self.rows
        return _window_rows(self.start_px.T, self.direction.T, self.length_px, self.tolerance_px)

    def bounds(self) -> tuple[F64, F64]:
        """((N, 2) lower, (N, 2) upper) corners of each window's bounding box."""
        d, tol = self.direction, self.tolerance_px
        p0 = self.start_px - tol * d
        p1 = self.start_px + (self.length_px + tol)[:, None] * d
        half = tol * np.abs(d[:, ::-1])  # the normal (-d_y, d_x), in absolute value
        return np.minimum(p0, p1) - half, np.maximum(p0, p1) + half

    def contains(self, left_idx: I64, right_uv_px: F64) -> BOOL:
        """(K,) whether right point k ((K, 2) `right_uv_px`) lies in the window of left
        keypoint `left_idx[k]`."""
        idx = np.asarray(left_idx, dtype=np.int64)
        right = np.asarray(right_uv_px, dtype=float).reshape(-1, 2).T
        inside = _inside(self.parameter_rows().take(idx, axis=1), right, self.tolerance_px)
        return inside & self.valid.take(idx)


def search_windows(
    left_uv_px: NDArray[np.floating], rig: StereoRig, z_min_m: float, tolerance_px: float
) -> SearchWindow:
    """The `SearchWindow` of each left keypoint (ideal left pixels), for depths >= z_min_m."""
    return _windows(left_uv_px, _rig_geometry(rig), z_min_m, tolerance_px)


def _windows(
    left_uv_px: NDArray[np.floating], geo: _RigGeometry, z_min_m: float, tolerance_px: float
) -> SearchWindow:
    """`search_windows` for a rig's `_RigGeometry`.

    With a = H_inf x_l and e = K_r t_rl (module docstring), the point at depth z projects to
    x_r(z) = (z a_xy + e_xy) / (z a_z + e_z): the segment starts at a_xy / a_z (z -> inf) and
    x_r(z) - a_xy / a_z = (a_z e_xy - e_z a_xy) / (a_z (z a_z + e_z)), so it runs along
    a_z e_xy - e_z a_xy whatever z, with length |a_z e_xy - e_z a_xy| / (a_z (z a_z + e_z))
    at the nearest depth (eq. 23 for a rectified pair: e = (-f b, 0, 0), a_z = 1: f b / z).
    Computed for all keypoints at once, on (2, N) arrays.
    """
    uv = np.asarray(left_uv_px, dtype=float).reshape(-1, 2)
    if geo.rows_only:
        return _row_windows(uv, geo, z_min_m, tolerance_px)
    H, e = geo.H_inf, geo.e
    a = H[:, :2] @ uv.T  # (3, N)
    a += H[:, 2:]
    a_z = a[2]
    valid = a_z > 1e-12  # far points of the ray lie in front of the right camera
    w = np.maximum(a_z, 1e-12)  # a_z where valid (the others are never searched)
    rows = np.empty((_ROWS, uv.shape[0]))
    start, direction = rows[0:2], rows[2:4]
    np.divide(a[:2], w, out=start)
    p = e[:2, None] * a_z
    p -= e[2] * a[:2]
    h = np.sqrt(p[0] * p[0] + p[1] * p[1])
    # nearest depth searched, pushed beyond the right camera's focal plane where needed
    z_near = np.maximum(z_min_m, (1e-6 - e[2]) / w)
    length = rows[8]
    np.divide(h, w * (z_near * w + e[2]), out=length)
    np.divide(p, np.maximum(h, 1e-300), out=direction)
    ok = length > 1e-9
    if not ok.all():  # the left point is the epipole (or the baseline is zero)
        direction[:, ~ok] = [[-1.0], [0.0]]
        length[~ok] = 0.0
    valid &= np.isfinite(start[0] + start[1] + length)
    rows[4] = direction[1]
    np.negative(direction[0], out=rows[5])
    np.multiply(length, 0.5, out=rows[6])
    np.add(rows[6], tolerance_px, out=rows[7])
    return SearchWindow(start.T, direction.T, length, valid, float(tolerance_px), rows)


def _row_windows(uv: F64, geo: _RigGeometry, z_min_m: float, tolerance_px: float) -> SearchWindow:
    """`_windows` of a rectified pair (`_RigGeometry.rows_only`), without the general
    arithmetic: the segment starts at x_l itself and runs along its row, towards -u for a
    right camera on the +x side, for HD_max = f b / z_min (eq. 20-23)."""
    n = uv.shape[0]
    e_u = float(geo.e[0])
    length = abs(e_u) / max(z_min_m, 1e-6)  # z_near = z_min: e_z = 0, a_z = 1
    rows = np.empty((_ROWS, n))
    rows[0:2] = uv.T
    if length > 1e-9:
        rows[2:6] = [[math.copysign(1.0, e_u)], [0.0], [0.0], [-math.copysign(1.0, e_u)]]
    else:  # zero baseline
        rows[2:6] = [[-1.0], [0.0], [0.0], [1.0]]
        length = 0.0
    rows[6:9] = [[0.5 * length], [0.5 * length + tolerance_px], [length]]
    valid = np.isfinite(rows[0] + rows[1])
    return SearchWindow(rows[0:2].T, rows[2:4].T, rows[8], valid, float(tolerance_px), rows)


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
    """(left, right) index pairs of every right keypoint inside every left window
    (`SearchWindow.contains`), sorted by left index, then by the right keypoints' coordinate
    across the epipolar lines.

    No loop over keypoints: the right keypoints are bucketed by their coordinate across the
    dominant epipolar direction (v, the image rows, for side-by-side rigs; u for stacked
    ones) with one stable sort; each window's extent along that coordinate gives its range
    of sorted right keypoints (one `searchsorted` for all windows); the ranges are expanded
    into (left, right) pairs and gathered at once (one gather of the window parameters, one
    of the right coordinates), then tested exactly (`_inside`). The extent is widened by
    1e-6 px so that rounding can only add pairs, which the exact test drops: the result is
    the exhaustive search's.
    """
    ruv = np.asarray(right_uv_px, dtype=float).reshape(-1, 2)
    n, m = len(window), ruv.shape[0]
    none = np.zeros(0, np.int64)
    if n == 0 or m == 0:
        return none, none.copy()
    rows, tol = window.parameter_rows(), window.tolerance_px
    # across the lines: v if most run along u
    axis = 1 if 2 * np.count_nonzero(np.abs(rows[2]) >= np.abs(rows[3])) >= n else 0
    right = ruv.T
    order = right[axis].argsort(kind="stable")
    right = right.take(order, axis=1)  # (2, M) sorted along `axis`
    coord = right[axis]
    # extent of each window along `axis`: the segment's midpoint +- half its length, plus
    # the band's half-width (`SearchWindow.bounds` on one axis)
    d_axis = rows[2 + axis]
    mid = rows[axis] + d_axis * rows[6]
    reach = np.abs(d_axis) * rows[7]
    reach += tol * np.abs(rows[3 - axis]) + 1e-6
    extent = np.empty(2 * n)
    np.subtract(mid, reach, out=extent[:n])
    np.add(mid, reach, out=extent[n:])
    first = coord.searchsorted(extent)  # the first sorted right keypoint >= each end
    lo = first[:n]
    counts = first[n:] - lo
    counts *= window.valid
    ends = counts.cumsum()
    total = int(ends[-1])
    if total == 0:
        return none, none.copy()
    left = np.repeat(np.arange(n, dtype=np.int64), counts)
    pos = np.arange(total, dtype=np.int64) + np.repeat(lo - (ends - counts), counts)
    inside = _inside(rows[:_TESTED].take(left, axis=1), right.take(pos, axis=1), tol)
    kept = inside.nonzero()[0]
    return left.take(kept), order.take(pos.take(kept))


_SCRATCH = threading.local()
_SCRATCH_PAIRS = 4096
"""Pairs per block of descriptor differences (4096 x 128 x 4 bytes of reused buffers)."""


def _scratch(rows: int, width: int) -> tuple[U8, U8, U16, F32]:
    """Reused per-thread work buffers for `rows` descriptor pairs: two uint8 and one uint16
    (rows, width), one float32 (rows, 1). Fresh buffers of a few hundred KiB per call can
    cost page faults (measured on the development machine: up to ~0.2 ms per frame, more
    than the whole matching)."""
    bufs = getattr(_SCRATCH, "bufs", None)
    if bufs is None or bufs[0].shape[0] < rows or bufs[0].shape[1] != width:
        size = max(rows, 1024)
        bufs = (
            np.empty((size, width), np.uint8),
            np.empty((size, width), np.uint8),
            np.empty((size, width), np.uint16),
            np.empty((size, 1), np.float32),
        )
        _SCRATCH.bufs = bufs
    return bufs[0][:rows], bufs[1][:rows], bufs[2][:rows], bufs[3][:rows]


def _descriptor_distances(left_desc: np.ndarray, right_desc: np.ndarray, li: I64, rj: I64) -> F32:
    """(K,) Euclidean descriptor distances D(i, j) = |d_i - d_j|_2 of the listed pairs, in
    float32, by whole-array operations on blocks of up to 4096 pairs.

    uint8 descriptors (SIFT's, integers <= 255): |a - b| in uint8 (`cv2.absdiff`), squares in
    uint16 (<= 65025), row sums in float32 (`cv2.reduce`), all exact (sums < 2^24), so the
    distances are the correctly rounded square roots whatever the order of summation. Other
    types: float32 differences, squares and sums (`np.einsum`)."""
    k = int(li.shape[0])
    out = np.empty(k, np.float32)
    step = _SCRATCH_PAIRS
    if left_desc.dtype == np.uint8 and right_desc.dtype == np.uint8:
        for s in range(0, k, step):
            a, b, sq, total = _scratch(min(step, k - s), left_desc.shape[1])
            np.take(left_desc, li[s : s + step], axis=0, out=a, mode="clip")  # valid indices
            np.take(right_desc, rj[s : s + step], axis=0, out=b, mode="clip")
            np.copyto(sq, cv2.absdiff(a, b, dst=a))
            np.multiply(sq, sq, out=sq)
            out[s : s + step] = cv2.reduce(sq, 1, cv2.REDUCE_SUM, dst=total, dtype=cv2.CV_32F)[:, 0]
    else:
        for s in range(0, k, step):
            d = left_desc.take(li[s : s + step], axis=0).astype(np.float32)
            d -= right_desc.take(rj[s : s + step], axis=0)
            np.einsum("ij,ij->i", d, d, out=out[s : s + step])
    return np.sqrt(out, out=out)


def _unrelated_pairs(n: int, m: int, count: int = 64) -> tuple[I64, I64]:
    """Up to `count` (left, right) pairs spread over both keypoint lists, with unrelated
    positions (a stride coprime to most list lengths), to estimate the distance between
    descriptors of different points."""
    k = min(count, n * m)
    i = np.arange(k, dtype=np.int64)
    return (i * n) // k, (i * 7919 + m // 2) % m


def _quantile_f32(values: F32, q: float) -> float:
    """`np.quantile(values, q)` (method "linear") of a 1-D float32 array, bit for bit, from a
    partial sort around the two neighbouring order statistics (np.quantile's general
    machinery costs ~20 times more on a few hundred values)."""
    k = int(values.shape[0])
    position = (k - 1) * q  # numpy's virtual index for "linear"
    j = math.floor(position)
    if j >= k - 1:
        return float(values.max())
    gamma = position - j
    part = np.partition(values, (j, j + 1))
    a, b = part[j], part[j + 1]
    diff = b - a  # float32; then numpy's _lerp, in float32 as numpy does it
    return float(b - diff * (1 - gamma)) if gamma >= 0.5 else float(a + diff * gamma)


_INF_KEY = np.int64(0x7F800000 << 32)
"""Sort key of 'no candidate': float32 +inf in the high half."""
_LOW = np.int64(0xFFFFFFFF)
_HIGH = 1 if sys.byteorder == "little" else 0
"""Index of a key's high half among its two 32-bit halves."""


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
    `cfg.left_right_check`, mutual consistency.

    left_uv_px: (N, 2), left_desc: (N, D); right_uv_px: (M, 2), right_desc: (M, D).

    A fixed sequence of whole-array operations, no loop over keypoints: windows
    (`search_windows`), candidate pairs gathered at once (`candidate_pairs`), their
    descriptor distances in one batched operation, then the two smallest distances per left
    keypoint and the smallest per right keypoint by unbuffered minimum reductions
    (`np.minimum.at`) over 64-bit keys (distance bits, then pair or left index: a
    non-negative float32 orders as its bit pattern), which also break ties by candidate order.
    """
    luv, ruv = _as_points(left_uv_px, "left"), _as_points(right_uv_px, "right")
    n, m = luv.shape[0], ruv.shape[0]
    ld, rd = _as_descriptors(left_desc, n, "left"), _as_descriptors(right_desc, m, "right")
    if ld.shape[1] != rd.shape[1]:
        raise ValueError(f"descriptor sizes differ: left {ld.shape[1]}, right {rd.shape[1]}")
    if n == 0 or m == 0:
        return StereoMatches.empty(n, m)
    geo = _rig_geometry(rig)
    window = _windows(luv, geo, _z_min(geo, cfg.z_min_m), cfg.vertical_tolerance_px)
    li, rj = candidate_pairs(window, ruv)
    k = int(li.shape[0])
    if k == 0:
        return StereoMatches.empty(n, m)
    dist = _descriptor_distances(ld, rd, li, rj)
    examined = k

    # D_min1, D_min2 per left keypoint (eq. before 20): keys (distance, pair index); pair k
    # is a spare slot, the "best pair" of keypoints without candidates
    bits = dist.view(np.int32).astype(np.int64)
    bits <<= 32
    key = np.empty(k + 1, np.int64)
    np.bitwise_or(bits, np.arange(k), out=key[:k])
    smallest = np.full(n, _INF_KEY | k)
    np.minimum.at(smallest, li, key[:k])
    best = smallest & _LOW
    key[best] = _INF_KEY  # each keypoint's best pair out of the way: the next is D_min2
    second = np.full(n, _INF_KEY)
    np.minimum.at(second, li, key[:k])
    d1 = smallest.view(np.float32)[_HIGH::2]  # the distance halves of the keys
    d2 = second.view(np.float32)[_HIGH::2]
    n_cand = np.bincount(li, minlength=n)
    # D1 < DistRatio * D2. A lone candidate has no D2 of its own: it is compared with the
    # typical distance to an unrelated keypoint (module docstring, "Lone candidates")
    lone = n_cand == 1
    if np.count_nonzero(lone):
        multi = n_cand >= 2
        if np.count_nonzero(multi) >= MIN_WINDOWS_FOR_TYPICAL_D2:
            d2_typical = _quantile_f32(d2[multi], LONE_D2_QUANTILE)
        else:
            li_r, rj_r = _unrelated_pairs(n, m)
            unrelated = _descriptor_distances(ld, rd, li_r, rj_r)
            d2_typical = _quantile_f32(unrelated, LONE_D2_QUANTILE)
            examined += int(li_r.shape[0])
        d2[lone] = d2_typical
    accept = d1 < cfg.dist_ratio * d2  # false without candidates (inf < inf)
    right_best = rj.take(best, mode="clip")
    if cfg.left_right_check:
        # the best left keypoint of each right one among all its pairs: keys (distance, left
        # index); a match stands if its own key is its right keypoint's smallest
        bits |= li
        nearest_left = np.full(m, _INF_KEY)
        np.minimum.at(nearest_left, rj, bits)
        accept &= nearest_left.take(right_best) == bits.take(best, mode="clip")
    sel = accept.nonzero()[0]
    right = right_best.take(sel)
    d1_sel = d1.take(sel)
    ratio = d1_sel / np.maximum(d2.take(sel), np.float32(1e-12))
    ratio[lone.take(sel)] = 0.0
    return StereoMatches(
        left=sel.astype(np.int64, copy=False),
        right=right.astype(np.int64, copy=False),
        disparity_px=(luv[:, 0].take(sel) - ruv[:, 0].take(right)).astype(np.float32),
        distance=d1_sel,
        ratio=ratio,
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
