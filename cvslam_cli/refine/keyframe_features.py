"""The stereo matches of a vehicle's keyframes, as re-association reads them (pure: a
`FeatureSet` in, flat arrays out): every accepted stereo match of each keyframe with its
measurement, its left descriptor, its triangulated point and the simulator's id.

A filter observation is one of these matches (the filter copies the match's undistorted
pixels into `observations.npz`); `find_rows` finds it again by its pixels, which gives the
observed landmark the descriptors it was seen with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, U8, check_shape
from cvslam_cli.records.features import FeatureSet

# a filter observation and its feature agree to float32 rounding of the pixels
SAME_PIXEL_TOL_PX = 1e-3


@dataclass(frozen=True, eq=False)
class KeyframeFeatures:
    """M stereo matches of K keyframes, CSR by keyframe: rows offsets[k]:offsets[k+1] are
    keyframe k's. z_px (M, 4) (u_l, v_l, u_r, v_r) undistorted pixels (eq. 19's
    measurement); desc (M, 128) uint8 the left keypoint's SIFT descriptor; p_cam_m (M, 3)
    the stereo point in the left camera frame (extract's triangulation); true_id (M,) the
    simulator's landmark id (-1 unknown, -2 an injected wrong match); size_px (2, 2) image
    width and height of the left and right cameras."""

    offsets: I64
    z_px: F64
    desc: U8
    p_cam_m: F64
    true_id: I64
    size_px: I64

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        check_shape("KeyframeFeatures.offsets", self.offsets, ("K+1",), "iu", dims)
        check_shape("KeyframeFeatures.z_px", self.z_px, ("M", 4), "f", dims)
        check_shape("KeyframeFeatures.desc", self.desc, ("M", "D"), "u", dims)
        check_shape("KeyframeFeatures.p_cam_m", self.p_cam_m, ("M", 3), "f", dims)
        check_shape("KeyframeFeatures.true_id", self.true_id, ("M",), "i", dims)
        check_shape("KeyframeFeatures.size_px", self.size_px, (2, 2), "iu", dims)
        if self.offsets[0] != 0 or self.offsets[-1] != len(self.z_px):
            raise ValueError("KeyframeFeatures.offsets: expected 0 .. M")

    @property
    def n_keyframes(self) -> int:
        return len(self.offsets) - 1

    def rows(self, k: int) -> slice:
        return slice(int(self.offsets[k]), int(self.offsets[k + 1]))

    def keyframe_of(self, rows: I64) -> I64:
        """(n,) the keyframe of each feature row."""
        return np.searchsorted(self.offsets, rows, side="right").astype(np.int64) - 1


def keyframe_features(fs: FeatureSet, stamps_ns: I64) -> KeyframeFeatures:
    """The stereo matches of the frames at `stamps_ns` (K,) (every stamp must be a frame of
    `fs`; ValueError naming the first that is not)."""
    frame_of = {int(s): i for i, s in enumerate(fs.frame_stamp_ns)}
    missing = [int(s) for s in stamps_ns if int(s) not in frame_of]
    if missing:
        raise ValueError(f"{fs.vehicle}: keyframe stamp {missing[0]} is no frame of the features")
    parts = [np.arange(*fs.frame_matches(frame_of[int(s)]).indices(len(fs.match_left)))
             for s in stamps_ns]  # fmt: skip
    counts = np.array([len(p) for p in parts], dtype=np.int64)
    m = np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
    ml, mr = fs.match_left[m], fs.match_right[m]
    z = np.concatenate([fs.left_uv_px[ml], fs.right_uv_px[mr]], axis=1).astype(float)
    return KeyframeFeatures(
        np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        z.reshape(-1, 4),
        fs.left_desc[ml].reshape(len(m), -1),
        fs.match_p_cam_m[m].reshape(-1, 3).astype(float),
        fs.match_landmark_id[m].astype(np.int64),
        np.asarray(fs.rig.size_px, dtype=np.int64),
    )


def find_rows(kf: KeyframeFeatures, keyframe: I64, z_px: F64) -> I64:
    """(n,) the feature row of each (keyframe, measurement z_px (n, 4)): the match of that
    keyframe with the same pixels, -1 when there is none (within SAME_PIXEL_TOL_PX)."""
    out = np.full(len(keyframe), -1, dtype=np.int64)
    for k in np.unique(keyframe):
        sel = np.flatnonzero(keyframe == k)
        rows = kf.rows(int(k))
        if rows.stop == rows.start:
            continue
        d = np.abs(z_px[sel, None, :] - kf.z_px[None, rows, :]).max(axis=2)  # (n_k, M_k)
        best = np.argmin(d, axis=1)
        ok = d[np.arange(len(sel)), best] < SAME_PIXEL_TOL_PX
        out[sel[ok]] = rows.start + best[ok]
    return out
