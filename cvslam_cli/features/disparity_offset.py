"""The stereo rig's disparity offset, estimated from the frames' own motion.

A rectified pair predicts the disparity of a point at depth z as d = f b / z + (c_l - c_r)
(f: focal length, b: baseline, c_l, c_r: the two principal points along x). When the right
camera's principal point is off by delta along x (an error of the calibration or of the
rectification), every measured disparity is off by the same d0 = -delta, and the depth of a
point measured at disparity d is off by the factor d / (d - d0): nothing near, many percent
far. Consecutive frames see the same points at different depths, so d0 shows as a depth-
dependent disagreement that no rigid motion explains, and the images alone determine it:
unlike a uniform scale error (a wrong baseline), which no camera-only data can tell from the
motion. (On the real KITTI clip b, whose stereo depth and ground truth "disagree in scale by
4-5 %", d0 is -1.2 px and explains that disagreement: BENCHMARKS.md, "Tenth step".)

The estimate: consecutive frame pairs (at most `max_pairs`, spread over the log); in each,
the stereo points of the earlier frame re-found in the later one by descriptor (ratio test),
the pair's motion from PnP with RANSAC (inliers and a starting point; `frame_pairs.py`),
then one robust least squares over every pair's motion and d0 together, on the later
frame's (u, v, d) as predicted from the earlier frame's (u, v, d). Its standard deviation is
the Gauss-Newton marginal of d0 scaled by the residuals' robust scale: the statistical
uncertainty only.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

from cvslam_cli.features.frame_pairs import (
    RectifiedIntrinsics,
    moved,
    pair_ks,
    pnp_inliers,
    predicted_uvd,
    refound,
)
from cvslam_cli.geometry.camera import StereoRig, stereo_rig
from cvslam_cli.geometry.stereo import triangulate_matches
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet

# Huber threshold of the joint solution (px); its evaluations (its Jacobian costs 7).
HUBER_PX = 1.0
MAX_EVALUATIONS = 300
# An offset adds the same to every disparity, a scale error multiplies them: only points at
# many depths tell them apart. Over flat ground seen from above (disparities within a few
# percent of each other) the offset is not determined from the images alone, and the
# estimate, which takes the earlier frame's points as exact, is biased by their noise
# (synthetic ground 60 m below: -5 px for a true 0); ahead of a car (KITTI, spread 0.6-0.9)
# it is determined (synthetic: within 0.02 px). Below this spread (standard deviation over
# mean of the disparities): not determined.
MIN_DISPARITY_SPREAD = 0.3
# Rounds of inlier selection and solution, until the offset moves less than this (px).
MAX_ROUNDS = 4
CONVERGED_PX = 0.01


@dataclass(frozen=True)
class DisparityOffset:
    """offset_px: measured minus calibrated disparity (px; the right camera's principal point
    is off by -offset_px along x); sigma_px: its standard deviation (statistical only); pairs,
    points: the frame pairs and re-found points it rests on; disparity_spread: standard
    deviation over mean of those points' disparities."""

    offset_px: float
    sigma_px: float
    pairs: int
    points: int
    disparity_spread: float

    @property
    def determined(self) -> bool:
        """Whether the points' disparities span enough to tell an offset from a scale
        (`MIN_DISPARITY_SPREAD`)."""
        return self.disparity_spread >= MIN_DISPARITY_SPREAD

    def depth_error(self, depth_m: float, rig: StereoRig) -> float:
        """Relative error of an uncorrected stereo depth at `depth_m` (positive: too far)."""
        d = rig.left.fx * rig.baseline_m / depth_m
        return float(d / (d + self.offset_px) - 1.0)


@dataclass(frozen=True)
class _Pairs:
    """Re-found points, one row each: the pair's index, (u, v, d) in the earlier frame
    (uvd0, (n, 3)) and in the later one (uvd1, (n, 3)); per pair a starting motion
    (rotation vector, translation: earlier camera -> later camera), (P, 6)."""

    pair: I64
    uvd0: F64
    uvd1: F64
    motion0: F64


def _residuals(params: F64, p: _Pairs, K: RectifiedIntrinsics) -> F64:
    """Later frame's (u, v, d) predicted minus measured, (3n,) in px."""
    offset, motion = params[0], params[1:].reshape(-1, 6)[p.pair]
    r = predicted_uvd(moved(p.uvd0, motion, K, offset), K, offset) - p.uvd1
    return r.T.ravel()


def _sparsity(p: _Pairs, n_pairs: int) -> csr_matrix:
    """Which parameters each residual depends on: the offset and its pair's motion."""
    n = len(p.pair)
    rows = np.repeat(np.arange(3 * n), 7)
    pair = np.tile(p.pair, 3)
    cols = np.column_stack([np.zeros(3 * n, dtype=np.int64), 1 + 6 * pair[:, None] + np.arange(6)])
    return csr_matrix((np.ones(rows.size), (rows, cols.ravel())), shape=(3 * n, 1 + 6 * n_pairs))


def estimate_disparity_offset(
    fs: FeatureSet, rig: StereoRig, max_pairs: int = 100
) -> DisparityOffset | None:
    """The disparity offset of `fs`'s rig from its consecutive frames (module docstring);
    None when the rig is not rectified or fewer than two frame pairs have enough points."""
    if not rig.rectified or fs.n_frames < 2:
        return None
    K = RectifiedIntrinsics.of(rig)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    ks = pair_ks(fs, max_pairs)
    candidates = [c for c in (refound(fs, int(k), K, matcher) for k in ks) if c is not None]
    offset, result = 0.0, None
    for _ in range(MAX_ROUNDS):
        solved = _solve(candidates, K, offset)
        if solved is None:
            return result
        moved, offset, result = abs(solved.offset_px - offset), solved.offset_px, solved
        if moved < CONVERGED_PX:
            break
    return result


def _solve(
    candidates: list[tuple[F64, F64]], K: RectifiedIntrinsics, offset: float
) -> DisparityOffset | None:
    """One round: each pair's inliers at `offset`, then every motion and the offset."""
    found = []
    for uvd0, uvd1 in candidates:
        inl = pnp_inliers(uvd0, uvd1, K, offset)
        if inl is not None:
            found.append((uvd0[inl[0]], uvd1[inl[0]], inl[1]))
    if len(found) < 2:
        return None
    pairs = _Pairs(
        pair=np.concatenate([np.full(len(u0), i) for i, (u0, _, _) in enumerate(found)]),
        uvd0=np.concatenate([u0 for u0, _, _ in found]),
        uvd1=np.concatenate([u1 for _, u1, _ in found]),
        motion0=np.array([m for _, _, m in found]),
    )
    x0 = np.concatenate([[offset], pairs.motion0.ravel()])
    sol = least_squares(
        _residuals, x0, args=(pairs, K), jac_sparsity=_sparsity(pairs, len(found)),
        loss="huber", f_scale=HUBER_PX, x_scale="jac", xtol=1e-12, max_nfev=MAX_EVALUATIONS,
    )  # fmt: skip
    return DisparityOffset(
        offset_px=float(sol.x[0]),
        sigma_px=_sigma(sol.jac, sol.fun),
        pairs=len(found),
        points=len(pairs.pair),
        disparity_spread=_spread(pairs.uvd0[:, 2] - K.c_lr - sol.x[0]),
    )


def _spread(d: F64) -> float:
    """Standard deviation over mean of the points' disparities."""
    return float(np.std(d) / np.mean(d)) if len(d) else 0.0


def _sigma(J: csr_matrix, r: F64) -> float:
    """The offset's standard deviation: its Gauss-Newton marginal, (J^T J)^-1 [0, 0], times
    the residuals' robust scale (1.4826 x their median absolute deviation)."""
    A = (J.T @ J).toarray() if hasattr(J, "toarray") else J.T @ J
    e0 = np.zeros(len(A))
    e0[0] = 1.0
    try:
        var = float(np.linalg.solve(A, e0)[0])
    except np.linalg.LinAlgError:
        return float("inf")
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return float(np.sqrt(max(var, 0.0)) * scale)


def apply_disparity_offset(
    fs: FeatureSet, offset_px: float, max_range_m: float, pixel_sigma_px: float
) -> tuple[FeatureSet, I64]:
    """`fs` with its rig's right principal point moved by -`offset_px` along x and every
    match triangulated again with it (a match whose point is no longer in front of both
    cameras and within `max_range_m` is dropped); and the matches kept per frame (F,)."""
    K = np.array(fs.rig.K, dtype=float, copy=True)
    K[1, 0, 2] -= offset_px
    rig = dataclasses.replace(fs.rig, K=K)
    p_cam, cov, keep = triangulate_matches(
        stereo_rig(rig),
        fs.left_uv_px[fs.match_left],
        fs.right_uv_px[fs.match_right],
        max_range_m,
        pixel_sigma_px,
    )
    frame = np.repeat(np.arange(fs.n_frames), np.diff(fs.match_offsets))
    per_frame = np.bincount(frame[keep], minlength=fs.n_frames).astype(np.int64)
    matches = {
        f.name: getattr(fs, f.name)[keep]
        for f in dataclasses.fields(fs)
        if f.name.startswith("match_") and f.name != "match_offsets"
    }
    out = dataclasses.replace(
        fs,
        rig=rig,
        match_offsets=np.concatenate([[0], np.cumsum(per_frame)]).astype(np.int64),
        **(matches | {"match_p_cam_m": p_cam[keep], "match_cov_cam_m2": cov}),
    )
    out.validate()
    return out, per_frame
