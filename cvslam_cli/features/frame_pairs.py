"""Consecutive frames of one rectified stereo rig: the stereo points of a frame re-found in
the next by descriptor, and the pair's motion by PnP with RANSAC. What the frames' own motion
says about the rig (`disparity_offset.py`) and about the keypoints' noise (`pixel_noise.py`).

A stereo point is (u, v, d): the left keypoint and the disparity d = u_l - u_r. In the left
camera it is X = ((u - c_x) z / f, (v - c_y) z / f_y, z), z = f b / (d - (c_l - c_r) - d0)
(f b: focal length times baseline; c_l - c_r: the calibrated disparity at infinity; d0: a
disparity offset, 0 unless estimated). Moved by a pair's motion (R, t: earlier camera ->
later camera), Y = R X + t, it is predicted in the later frame at

    (f Y_x / Y_z + c_x,  f_y Y_y / Y_z + c_y,  f b / Y_z + (c_l - c_r) + d0).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet

# A frame pair counts with at least this many PnP inliers.
MIN_PAIR_POINTS = 12
# Points nearer to zero disparity than this (px) say little about depth and are unstable
# under a disparity offset.
MIN_DISPARITY_PX = 2.0
# Re-found points: descriptor ratio test; PnP's inlier threshold (px).
DESCRIPTOR_RATIO = 0.8
PNP_INLIER_PX = 3.0


@dataclass(frozen=True)
class RectifiedIntrinsics:
    """What the (u, v, d) of a rectified rig's points need: the left camera's f, f_y, c_x,
    c_y, f b and c_lr = c_l - c_r (the calibrated disparity at infinity)."""

    f: float
    fy: float
    cx: float
    cy: float
    fb: float
    c_lr: float

    @classmethod
    def of(cls, rig: StereoRig) -> RectifiedIntrinsics:
        f = rig.left.fx
        return cls(
            f, rig.left.fy, rig.left.cx, rig.left.cy, f * rig.baseline_m, rig.left.cx - rig.right.cx
        )

    @property
    def K(self) -> F64:
        """(3, 3) the left camera matrix."""
        return np.array([[self.f, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def frame_points(fs: FeatureSet, k: int) -> tuple[F64, np.ndarray]:
    """Frame k's stereo points (n, 3) as (u, v, d) and their left descriptors (n, D)."""
    sl = fs.frame_matches(k)
    left = fs.match_left[sl]
    uvd = np.column_stack(
        [fs.left_uv_px[left].astype(float), fs.match_disparity_px[sl].astype(float)]
    )
    return uvd, fs.left_desc[left].astype(np.float32)


def points(uvd: F64, K: RectifiedIntrinsics, offset: float | F64 = 0.0) -> F64:
    """(n, 3) points in the left camera from (u, v, d) with the disparity offset removed."""
    z = K.fb / (uvd[:, 2] - K.c_lr - offset)
    return np.column_stack([(uvd[:, 0] - K.cx) * z / K.f, (uvd[:, 1] - K.cy) * z / K.fy, z])


def pair_ks(fs: FeatureSet, max_pairs: int) -> I64:
    """The earlier frames of at most `max_pairs` consecutive pairs, spread over the log."""
    n = min(max_pairs, fs.n_frames - 1)
    return np.unique(np.linspace(0, fs.n_frames - 2, n).round().astype(np.int64))


def refound(
    fs: FeatureSet, k: int, K: RectifiedIntrinsics, matcher: cv2.BFMatcher
) -> tuple[F64, F64] | None:
    """(uvd0, uvd1): the stereo points of frame k re-found in frame k + 1 by descriptor
    (ratio test), both away from zero disparity; None with fewer than MIN_PAIR_POINTS."""
    uvd0, desc0 = frame_points(fs, k)
    uvd1, desc1 = frame_points(fs, k + 1)
    if len(uvd0) < MIN_PAIR_POINTS or len(uvd1) < MIN_PAIR_POINTS:
        return None
    found = [
        (m[0].queryIdx, m[0].trainIdx)
        for m in matcher.knnMatch(desc0, desc1, k=2)
        if len(m) == 2 and m[0].distance < DESCRIPTOR_RATIO * m[1].distance
    ]
    if len(found) < MIN_PAIR_POINTS:
        return None
    i, j = np.array(found).T
    near = (uvd0[i, 2] - K.c_lr > MIN_DISPARITY_PX) & (uvd1[j, 2] - K.c_lr > MIN_DISPARITY_PX)
    if near.sum() < MIN_PAIR_POINTS:
        return None
    return uvd0[i[near]], uvd1[j[near]]


def pnp_inliers(
    uvd0: F64, uvd1: F64, K: RectifiedIntrinsics, offset: float = 0.0
) -> tuple[I64, F64] | None:
    """(rows, motion): one pair's PnP inliers and its motion (rotation vector, translation;
    (6,)), with the earlier frame's points at the depths `offset` gives them; None with
    fewer than MIN_PAIR_POINTS inliers."""
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        points(uvd0, K, offset), uvd1[:, :2], K.K, None, reprojectionError=PNP_INLIER_PX,
        iterationsCount=200, confidence=0.999, flags=cv2.SOLVEPNP_EPNP,
    )  # fmt: skip
    if not ok or inliers is None or len(inliers) < MIN_PAIR_POINTS:
        return None
    return inliers[:, 0], np.concatenate([rvec.ravel(), tvec.ravel()])


def moved(uvd0: F64, motion: F64, K: RectifiedIntrinsics, offset: float | F64 = 0.0) -> F64:
    """(n, 3): the earlier frame's points in the later camera, Y = R X + t, with one motion
    (6,) or one per point (n, 6) (module docstring)."""
    X = points(uvd0, K, offset)
    if motion.ndim == 1:
        return X @ Rotation.from_rotvec(motion[:3]).as_matrix().T + motion[3:]
    R = Rotation.from_rotvec(motion[:, :3]).as_matrix()
    return np.einsum("nij,nj->ni", R, X) + motion[:, 3:]


def predicted_uvd(Y: F64, K: RectifiedIntrinsics, offset: float | F64 = 0.0) -> F64:
    """(n, 3): points Y (n, 3) in the later camera as (u, v, d) (module docstring)."""
    z = Y[:, 2]
    return np.column_stack(
        [K.f * Y[:, 0] / z + K.cx, K.fy * Y[:, 1] / z + K.cy, K.fb / z + K.c_lr + offset]
    )
