"""The descriptor test of stereo matching (paper, "Stereo vision constraints"), inside the
search windows of eq. 20-34 (`windows.py`).

Descriptor distance (unnumbered, before eq. 20): D(i, j) = |d_i - d_j|_2. A left keypoint i is
matched to the right keypoint k of smallest distance D1 if D1 < DistRatio * D2, D2 being the
second smallest; the paper compares i only with the right keypoints inside its window instead
of all M of them (M x 128 operations per left keypoint). `left_right_check` keeps a match only
if its left keypoint is also the best among the candidates of its right keypoint.

Lone candidates (an addition to the paper). A window holding a single right keypoint has no
second-best distance, and accepting its candidate unconditionally lets any unlike keypoint
through when the true match was not detected: on rendered stereo pairs most wrong matches were
such lone candidates, with distances typical of unrelated descriptors. A wrong lone candidate
is one draw from the distribution of distances to unrelated keypoints, which the second-best
distances D2 of the windows with two or more candidates sample; the lone candidate's D2 is the
lower quartile of those (of 64 spread-out (left, right) pairs, counted in
`candidates_examined`, when fewer than 8 such windows exist), so it passes the ratio test only
when clearly nearer than most unrelated keypoints (precision and recall of the choices:
BENCHMARKS.md, "Feature extraction (issue 4)", "Lone candidates"). Their `ratio` is reported
as 0.

`match_stereo` is a fixed sequence of whole-array operations with no loop over keypoints; the
plain statement of the same rules, which the tests compare it with, is
tests/features/reference_matcher.py.
"""

from __future__ import annotations

import math
import sys
import threading
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.config import StereoMatchConfig
from cvslam_cli.features.windows import auto_z_min_m, candidate_pairs, search_windows
from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.records.arrays import F32, F64, I64, U8, U16, BoolArray
from cvslam_cli.records.features import DESCRIPTOR_SIZE

MIN_WINDOWS_FOR_TYPICAL_D2 = 8
"""Windows with >= 2 candidates needed to take the typical D2 from them (else random pairs)."""
LONE_D2_QUANTILE = 0.25
"""A lone candidate's D2: this quantile of the second-best distances of the other windows."""
UNRELATED_PAIRS = 64
"""(left, right) pairs sampled for the typical unrelated distance when windows are too few."""


@dataclass(frozen=True, eq=False)
class StereoMatches:
    """Matches between N_left and N_right keypoints of one stereo pair (M of them), sorted by
    left index.

    left, right: (M,) int64 indices into the left and right keypoint arrays.
    disparity_px: (M,) float32 u_l - u_r in ideal pixels.
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
        return np.zeros((0, d.shape[1] if d.ndim == 2 else DESCRIPTOR_SIZE), d.dtype)
    if d.ndim != 2 or d.shape[0] != n:
        raise ValueError(f"{side} descriptors: expected ({n}, D) for {n} keypoints, got {d.shape}")
    return d


# -- descriptor distances ---------------------------------------------------------------------

_SCRATCH = threading.local()
_SCRATCH_PAIRS = 4096
"""Pairs per block of descriptor differences (4096 x 128 x 4 bytes of reused buffers)."""


def _scratch(rows: int, width: int) -> tuple[U8, U8, U16, F32]:
    """Reused per-thread work buffers for `rows` descriptor pairs: two uint8 and one uint16
    (rows, width), one float32 (rows, 1). Fresh buffers of a few hundred KiB per call can
    cost page faults worth more than the whole matching (BENCHMARKS.md, "Leaner stereo
    matcher")."""
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
    """(K,) Euclidean descriptor distances D(i, j) = |d_i - d_j|_2 of the listed pairs
    (unnumbered, before eq. 20), in float32, by whole-array operations on blocks of up to
    `_SCRATCH_PAIRS` pairs (`_squared_distances_u8` for SIFT's uint8 descriptors, else
    `_squared_distances_float`)."""
    k = int(li.shape[0])
    out = np.empty(k, np.float32)
    exact = left_desc.dtype == np.uint8 and right_desc.dtype == np.uint8
    squared = _squared_distances_u8 if exact else _squared_distances_float
    for s in range(0, k, _SCRATCH_PAIRS):
        block = slice(s, s + _SCRATCH_PAIRS)
        squared(left_desc, right_desc, li[block], rj[block], out[block])
    return np.sqrt(out, out=out)


def _squared_distances_u8(left_desc: U8, right_desc: U8, li: I64, rj: I64, out: F32) -> None:
    """Squared distances of uint8 descriptor pairs into `out`, exactly: |a - b| in uint8
    (`cv2.absdiff`), squares in uint16 (<= 65025), row sums in float32 (`cv2.reduce`; sums <
    2^24), in the `_scratch` buffers; so the distances are the correctly rounded square roots
    whatever the order of summation."""
    a, b, sq, total = _scratch(int(li.shape[0]), left_desc.shape[1])
    np.take(left_desc, li, axis=0, out=a, mode="clip")  # valid indices
    np.take(right_desc, rj, axis=0, out=b, mode="clip")
    np.copyto(sq, cv2.absdiff(a, b, dst=a))
    np.multiply(sq, sq, out=sq)
    out[:] = cv2.reduce(sq, 1, cv2.REDUCE_SUM, dst=total, dtype=cv2.CV_32F)[:, 0]


def _squared_distances_float(
    left_desc: np.ndarray, right_desc: np.ndarray, li: I64, rj: I64, out: F32
) -> None:
    """Squared distances of other descriptor pairs into `out`: float32 differences, squares
    and sums (`np.einsum`)."""
    d = left_desc.take(li, axis=0).astype(np.float32)
    d -= right_desc.take(rj, axis=0)
    np.einsum("ij,ij->i", d, d, out=out)


# -- D1, D2 and the left-right check ------------------------------------------------------------

_INF_KEY = np.int64(0x7F800000 << 32)
"""Sort key of 'no candidate': float32 +inf in the high half."""
_LOW = np.int64(0xFFFFFFFF)
_HIGH = 1 if sys.byteorder == "little" else 0
"""Index of a key's high half among its two 32-bit halves."""


def _distance_keys(dist: F32) -> I64:
    """(K,) int64 sort keys with the bits of the (non-negative) float32 distances in the high
    half and the low half zero, for an index to be OR-ed in. A non-negative float32 orders as
    its bit pattern, so the smallest key is the smallest distance, ties going to the smallest
    index; one unbuffered `np.minimum.at` then finds a group's best pair and its index
    together."""
    keys = dist.view(np.int32).astype(np.int64)
    keys <<= 32
    return keys


def _two_smallest_per_left(keys: I64, li: I64, n: int) -> tuple[I64, F32, F32]:
    """For each of n left keypoints, over its candidate pairs (pair p: left keypoint li[p],
    distance key keys[p]): the best pair's index (K, a spare slot, when it has none), D1 and
    D2 (float32, +inf where missing). Ties go to the earlier pair."""
    k = int(li.shape[0])
    key = np.empty(k + 1, np.int64)  # pair k: the "best pair" of keypoints without candidates
    np.bitwise_or(keys, np.arange(k), out=key[:k])
    smallest = np.full(n, _INF_KEY | k)
    np.minimum.at(smallest, li, key[:k])
    best = smallest & _LOW
    key[best] = _INF_KEY  # each keypoint's best pair out of the way: the next is D2
    second = np.full(n, _INF_KEY)
    np.minimum.at(second, li, key[:k])
    return best, smallest.view(np.float32)[_HIGH::2], second.view(np.float32)[_HIGH::2]


def _mutual_best(keys: I64, li: I64, rj: I64, best: I64, m: int) -> BoolArray:
    """(n,) whether each left keypoint's best pair `best` is also the best pair of its right
    keypoint among all that right keypoint's pairs (ties to the smaller left index);
    meaningless for left keypoints without candidates, which the ratio test rejects."""
    left_keys = keys | li
    nearest_left = np.full(m, _INF_KEY)
    np.minimum.at(nearest_left, rj, left_keys)
    return nearest_left.take(rj.take(best, mode="clip")) == left_keys.take(best, mode="clip")


# -- lone candidates ------------------------------------------------------------------------------


def _unrelated_pairs(n: int, m: int, count: int = UNRELATED_PAIRS) -> tuple[I64, I64]:
    """Up to `count` (left, right) pairs spread over both keypoint lists, with unrelated
    positions (a stride coprime to most list lengths), to estimate the distance between
    descriptors of different points."""
    k = min(count, n * m)
    i = np.arange(k, dtype=np.int64)
    return (i * n) // k, (i * 7919 + m // 2) % m


def _quantile_f32(values: F32, q: float) -> float:
    """`np.quantile(values, q)` (method "linear") of a 1-D float32 array, bit for bit, from a
    partial sort around the two neighbouring order statistics (np.quantile's general
    machinery costs many times more on a few hundred values)."""
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


def _lone_candidate_d2(
    d2: F32, n_cand: I64, left_desc: np.ndarray, right_desc: np.ndarray
) -> tuple[float, int]:
    """The D2 a lone candidate is tested against (module docstring, "Lone candidates"): the
    `LONE_D2_QUANTILE` of the D2 of the windows with two or more candidates, or when fewer than
    `MIN_WINDOWS_FOR_TYPICAL_D2` of those, of the distances of `_unrelated_pairs`; and the
    number of extra descriptor pairs compared for it."""
    multi = n_cand >= 2
    if np.count_nonzero(multi) >= MIN_WINDOWS_FOR_TYPICAL_D2:
        return _quantile_f32(d2[multi], LONE_D2_QUANTILE), 0
    li, rj = _unrelated_pairs(left_desc.shape[0], right_desc.shape[0])
    unrelated = _descriptor_distances(left_desc, right_desc, li, rj)
    return _quantile_f32(unrelated, LONE_D2_QUANTILE), int(li.shape[0])


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
    descriptor distances in one batched operation, the two smallest distances per left
    keypoint (`_two_smallest_per_left`) and the left-right check (`_mutual_best`) by
    minimum reductions over 64-bit keys, which also break ties by candidate order.
    """
    luv, ruv = _as_points(left_uv_px, "left"), _as_points(right_uv_px, "right")
    n, m = luv.shape[0], ruv.shape[0]
    ld, rd = _as_descriptors(left_desc, n, "left"), _as_descriptors(right_desc, m, "right")
    if ld.shape[1] != rd.shape[1]:
        raise ValueError(f"descriptor sizes differ: left {ld.shape[1]}, right {rd.shape[1]}")
    if n == 0 or m == 0:
        return StereoMatches.empty(n, m)
    z_min_m = auto_z_min_m(rig, cfg.z_min_m)
    window = search_windows(luv, rig, z_min_m, cfg.vertical_tolerance_px)  # eq. 20-34
    li, rj = candidate_pairs(window, ruv)
    k = int(li.shape[0])
    if k == 0:
        return StereoMatches.empty(n, m)
    keys = _distance_keys(_descriptor_distances(ld, rd, li, rj))
    best, d1, d2 = _two_smallest_per_left(keys, li, n)  # D_min1, D_min2 (before eq. 20)
    examined = k
    n_cand = np.bincount(li, minlength=n)
    lone = n_cand == 1
    if np.count_nonzero(lone):
        d2_lone, extra = _lone_candidate_d2(d2, n_cand, ld, rd)
        d2[lone] = d2_lone
        examined += extra
    accept = d1 < cfg.dist_ratio * d2  # D1 < DistRatio D2; false without candidates (inf < inf)
    if cfg.left_right_check:
        accept &= _mutual_best(keys, li, rj, best, m)
    sel = accept.nonzero()[0]
    right = rj.take(best.take(sel))
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
