"""The stereo search windows of eq. 20-34 (paper, "Stereo vision constraints" and "Disparity
analysis"): where in the right image the match of a left keypoint can lie.

The paper bounds the search by the depths that can occur: horizontal disparity up to
HD_max = f b / z_min (eq. 20-23: z = f b / d, nothing is nearer than z_min), and vertical
distance up to VD_max = |A| HD_max from the epipolar line v_r = A u_r + B of the fundamental
matrix (eq. 24-29: p_r^T F p_l = 0; eq. 30-34: the window; a pixel or two once rectified).
The paper centres the window on u_l (eq. 30, half-width HD_max / 2); the sign of the
disparity being known, the window here runs from zero disparity to HD_max.

One mechanism for rectified and unrectified rigs. All coordinates are *ideal* pixels (lens
distortion removed, each camera's own K; `undistort_keypoints`). The point at depth z on the
ray of left pixel x_l projects into the right image at

    x_r(z) ~ z H_inf x_l + K_r t_rl,      H_inf = K_r R_rl K_l^-1,

(R_rl, t_rl: left camera frame -> right camera frame), a straight segment as z runs from z_min
to infinity: from x_r(z_min) to the image of the ray's point at infinity, H_inf x_l. This is
the epipolar line of x_l (F = K_r^-T [t_rl]x R_rl K_l^-1, eq. 24-25) cut to the depths that
can occur. For a rectified pair H_inf = I and the segment is the row of x_l from disparity 0 to
HD_max = f b / z_min. The window is that segment widened by `vertical_tolerance_px` (VD_max,
eq. 34) across the line and by the same amount beyond both ends.

No loop over keypoints (a few hundred keypoints per image make numpy's per-call overhead, not
arithmetic, the cost): all windows at once (`search_windows`, on (2, N) arrays), and all
(left, right) pairs inside them at once (`candidate_pairs`, a bucket search exact to the
window test). The plain per-pair statement of the same windows is the tests' reference
matcher (tests/features/reference_matcher.py).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.projection import undistort_pixels
from cvslam_cli.geometry.rotations import invert_T
from cvslam_cli.records.arrays import F64, I64, BoolArray

AUTO_Z_MIN_BASELINES = 4.0
"""`z_min_m: 0` means max(AUTO_Z_MIN_FLOOR_M, AUTO_Z_MIN_BASELINES * baseline)."""
AUTO_Z_MIN_FLOOR_M = 0.5


def undistort_keypoints(cam: CameraModel, uv_raw_px: NDArray[np.floating]) -> F64:
    """(N, 2) raw pixel coordinates -> (N, 2) ideal pinhole pixels of the camera's own K
    (u = fx x + s y + cx, v = fy y + cy with (x, y) the undistorted normalised coordinates):
    the coordinates the windows are in."""
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
    """The nearest depth searched (z_min of eq. 23): `z_min_m`, or when 0 max(0.5 m,
    4 baselines)."""
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


_ROWS = 9
"""Rows of a window parameter block, one column per window: start (2), direction d (2),
(d_y, -d_x) (2), length / 2, length / 2 + tolerance, length. Computing the derived rows once
per window and keeping them in one (9, N) array lets the candidate search gather everything
the window test reads for K pairs in one `take`. The first `_TESTED` rows are what the window
test (`_inside`) reads."""
_TESTED = 8


def _inside(rows: F64, right: F64, tolerance_px: float) -> BoolArray:
    """(K,) whether right point `right[:, k]` ((2, K)) lies in the window whose parameter
    block (`_ROWS`) is `rows[:, k]` (eq. 30-34): within `tolerance_px` of the epipolar line,
    and from `tolerance_px` before the segment's start to `tolerance_px` beyond its end
    (|along - length / 2| <= length / 2 + tolerance)."""
    rel = right - rows[0:2]
    x = rel[0] * rows[2:4]  # (along, across) = (rel . d, rel x d)
    x += rel[1] * rows[4:6]
    x[0] -= rows[6]
    np.abs(x, out=x)
    return (x[0] <= rows[7]) & (x[1] <= tolerance_px)


@dataclass(frozen=True, eq=False)
class SearchWindow:
    """Where the right-image match of each of N left keypoints may lie (ideal right pixels).

    rows: (9, N) parameter block of the windows (layout: `_ROWS`), read through
        `start_px`, `direction` and `length_px`.
    valid: (N,) the ray has points beyond z_min in front of the right camera.
    tolerance_px: half-width of the band around the segment, and slack beyond its ends
        (VD_max, eq. 34).
    """

    rows: F64
    valid: BoolArray
    tolerance_px: float

    def __len__(self) -> int:
        return int(self.rows.shape[1])

    @property
    def start_px(self) -> F64:
        """(N, 2) image of the left ray's point at infinity (zero disparity)."""
        return self.rows[0:2].T

    @property
    def direction(self) -> F64:
        """(N, 2) unit vector along the epipolar line from `start_px` towards nearer depths."""
        return self.rows[2:4].T

    @property
    def length_px(self) -> F64:
        """(N,) segment length to the image of the point at z_min (for a rectified pair
        HD_max = f b / z_min, eq. 23)."""
        return self.rows[8]

    def contains(self, left_idx: I64, right_uv_px: F64) -> BoolArray:
        """(K,) whether right point k ((K, 2) `right_uv_px`) lies in the window of left
        keypoint `left_idx[k]`."""
        idx = np.asarray(left_idx, dtype=np.int64)
        right = np.asarray(right_uv_px, dtype=float).reshape(-1, 2).T
        inside = _inside(self.rows.take(idx, axis=1), right, self.tolerance_px)
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
    return SearchWindow(rows, valid, float(tolerance_px))


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
    return SearchWindow(rows, valid, float(tolerance_px))


def candidate_pairs(window: SearchWindow, right_uv_px: F64) -> tuple[I64, I64]:
    """(left, right) index pairs of every right keypoint inside every left window
    (`SearchWindow.contains`), sorted by left index, then by the right keypoints' coordinate
    across the epipolar lines.

    No loop over keypoints: the right keypoints are sorted once by their coordinate across the
    dominant epipolar direction (`_across_axis`); each window's extent along that coordinate
    (`_window_extents`) gives its range of sorted right keypoints (one `searchsorted` for all
    windows); the ranges are expanded into (left, right) pairs (`_expand_ranges`) and gathered
    at once (one gather of the window parameters, one of the right coordinates), then tested
    exactly (`_inside`). The extents are widened so that rounding can only add pairs, which
    the exact test drops: the result is the exhaustive search's.
    """
    ruv = np.asarray(right_uv_px, dtype=float).reshape(-1, 2)
    n, m = len(window), ruv.shape[0]
    none = np.zeros(0, np.int64)
    if n == 0 or m == 0:
        return none, none.copy()
    rows, tol = window.rows, window.tolerance_px
    axis = _across_axis(rows)
    right = ruv.T
    order = right[axis].argsort(kind="stable")
    right = right.take(order, axis=1)  # (2, M) sorted along `axis`
    first = right[axis].searchsorted(_window_extents(rows, axis, tol))
    lo = first[:n]  # the first sorted right keypoint >= each window's lower end
    counts = first[n:] - lo
    counts *= window.valid
    left, pos = _expand_ranges(lo, counts)
    if left.shape[0] == 0:
        return none, none.copy()
    inside = _inside(rows[:_TESTED].take(left, axis=1), right.take(pos, axis=1), tol)
    kept = inside.nonzero()[0]
    return left.take(kept), order.take(pos.take(kept))


def _across_axis(rows: F64) -> int:
    """The image axis across most epipolar lines, to bucket the right keypoints by: 1 (v,
    the image rows) when most lines run along u, as for side-by-side rigs; 0 (u) otherwise,
    as for stacked ones."""
    n = rows.shape[1]
    return 1 if 2 * np.count_nonzero(np.abs(rows[2]) >= np.abs(rows[3])) >= n else 0


def _window_extents(rows: F64, axis: int, tolerance_px: float) -> F64:
    """(2N,) lower ends of the N windows along image axis `axis`, then their upper ends: the
    segment's midpoint +- half its length and the band's half-width (the window's bounding
    box on that axis), widened by 1e-6 px so that rounding can only add candidates."""
    n = rows.shape[1]
    d_axis = rows[2 + axis]
    mid = rows[axis] + d_axis * rows[6]
    reach = np.abs(d_axis) * rows[7]
    reach += tolerance_px * np.abs(rows[3 - axis]) + 1e-6
    extent = np.empty(2 * n)
    np.subtract(mid, reach, out=extent[:n])
    np.add(mid, reach, out=extent[n:])
    return extent


def _expand_ranges(lo: I64, counts: I64) -> tuple[I64, I64]:
    """Window w's range [lo[w], lo[w] + counts[w]) of sorted right keypoints, for every w,
    expanded into (window index, position) pairs in window order, without a loop: positions
    are a running index offset by each range's start minus the pairs before it."""
    ends = counts.cumsum()
    total = int(ends[-1])
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    left = np.repeat(np.arange(lo.shape[0], dtype=np.int64), counts)
    pos = np.arange(total, dtype=np.int64) + np.repeat(lo - (ends - counts), counts)
    return left, pos
