"""Tracks of the stereo matches no landmark claimed, across consecutive keyframes of one
vehicle (pure numpy): the points the filter never mapped (its state is bounded, it adds at
most a few landmarks a frame), which the batch can afford.

A free match of keyframe k, its stereo point (extract's triangulation, left camera frame)
carried to the nav frame with the pose of k, is predicted into keyframe k+1 with that pose
(eq. 19) and guided-matched (`guided_matching.match`: pixel gate on both images, descriptor
ratio test, one to one) with k+1's free matches. Links chain into tracks; a track seen in at
least `min_keyframes` keyframes becomes a new point, placed at the stereo point of its
nearest observation (the most precise triangulation: the depth error grows with depth^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, BoolArray
from cvslam_cli.refine.guided_matching import in_images, match, project
from cvslam_cli.refine.keyframe_features import KeyframeFeatures


@dataclass(frozen=True, eq=False)
class Tracks:
    """T tracks over n feature rows: `track` (n,) in 0..T-1 and `feature` (n,) rows of the
    vehicle's `KeyframeFeatures` (sorted by track, then keyframe); `p_nav_m` (T, 3) each
    track's initial position."""

    track: I64
    feature: I64
    p_nav_m: F64

    def __len__(self) -> int:
        return len(self.p_nav_m)


def stereo_points_nav(T_nav_body: F64, T_body_cam_left: F64, p_cam_m: F64) -> F64:
    """(n, 3) left-camera points p_cam_m (n, 3) in the nav frame from pose T_nav_body."""
    T = T_nav_body @ T_body_cam_left
    return p_cam_m @ T[:3, :3].T + T[:3, 3]


def track_free_features(
    poses: F64,
    K_px: F64,
    T_body_cam: F64,
    kf: KeyframeFeatures,
    free: BoolArray,
    radius_px: float,
    ratio: float,
    max_distance: float,
    min_keyframes: int,
) -> Tracks:
    """Tracks (module docstring) of the rows of `kf` where `free` (M,) is True, with the
    keyframe poses `poses` (K, 4, 4) and the rig K_px (2, 3, 3), T_body_cam (2, 4, 4)."""
    M = len(kf.z_px)
    track_of = np.full(M, -1, dtype=np.int64)
    n_tracks = 0
    for k in range(kf.n_keyframes - 1):
        a = np.arange(*kf.rows(k).indices(M))
        b = np.arange(*kf.rows(k + 1).indices(M))
        a, b = a[free[a]], b[free[b]]
        if not len(a) or not len(b):
            continue
        p = stereo_points_nav(poses[k], T_body_cam[0], kf.p_cam_m[a])
        z, depth = project(poses[k + 1], K_px, T_body_cam, p)
        seen = np.flatnonzero(in_images(z, depth, kf.size_px))
        if not len(seen):
            continue
        m = match(
            z[seen], kf.desc[a[seen]][:, None, :], np.ones(len(seen), dtype=np.int64),
            kf.z_px[b], kf.desc[b], radius_px, ratio, max_distance,
        )  # fmt: skip
        src, dst = a[seen[m.point]], b[m.feature]
        fresh = track_of[src] < 0
        track_of[src[fresh]] = n_tracks + np.arange(int(fresh.sum()))
        n_tracks += int(fresh.sum())
        track_of[dst] = track_of[src]
    rows = np.flatnonzero(track_of >= 0)
    ids, counts = np.unique(track_of[rows], return_counts=True)
    good = ids[counts >= min_keyframes]
    rows = rows[np.isin(track_of[rows], good)]
    track = np.searchsorted(good, track_of[rows]).astype(np.int64)
    order = np.lexsort((rows, track))
    track, rows = track[order], rows[order]
    # each track's nearest observation places it
    keyframe = kf.keyframe_of(rows)
    depth = kf.p_cam_m[rows, 2]
    p = np.zeros((len(good), 3))
    if len(rows):
        nearest = np.lexsort((depth, track))
        first = nearest[np.r_[True, track[nearest][1:] != track[nearest][:-1]]]
        for t, r, k in zip(track[first], rows[first], keyframe[first], strict=True):
            p[t] = stereo_points_nav(poses[k], T_body_cam[0], kf.p_cam_m[r : r + 1])[0]
    return Tracks(track, rows, p)
