"""Handing the last landmarks of an anchor to a newer one (anchored inverse depth).

Every anchor clone costs 6 numbers of the state (`landmark_coordinates.py`). Its landmarks
leave one by one (evicted), or come back a few at a time on a clone of their own
(re-activation), and an anchor holding a handful is 6 numbers for a few times 3: a tenth of
a two-UAV state is such anchors, and the update's cost grows with the square of the state.
So when a vehicle clones a new anchor for its new landmarks, the landmarks of every anchor
holding at most `max_landmarks` are written relative to it instead, and their old anchors
leave the state (BENCHMARKS.md, "Fuse: light anchors handed over").
The nav-frame points do not move: theta' = from_nav(to_nav(a, theta), a') is an exact
change of coordinates, and the covariance follows it through its Jacobian at the estimate
(`JointState.reanchor`). OpenVINS does the same when a SLAM feature's anchor clone leaves
its window (`UpdaterSLAM::change_anchors`). Only landmarks the new anchor's left camera
sees (in front of it, inside its image) are moved: written relative to a camera that does
not see it, a point's depth uncertainty is no longer along that camera's ray, and inverse
depth is no longer the coordinate it is Gaussian in (handing over every light anchor of a
4-UAV team, wherever it was, cost uav3 0.19 -> 0.33 m); an anchor with a landmark out of
view keeps all of its own.
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.landmark_coordinates import AnchoredInverseDepth
from cvslam_cli.estimation.state import JointState
from cvslam_cli.records.arrays import F64

# Landmarks nearer to the new anchor's left camera than this (m, along its axis) stay.
MIN_DEPTH_M = 0.5


def hand_over(
    state: JointState,
    key: int,
    R_cam_body: F64,
    t_body_cam: F64,
    K: F64,
    size_px: tuple[int, int],
    max_landmarks: int,
) -> int:
    """Write the landmarks of every unpinned anchor holding 1 to `max_landmarks` of them
    relative to the anchor `key`, whose left camera is R_cam_body, t_body_cam with
    intrinsics K (3, 3) and image size (width, height); an anchor with a landmark that
    camera does not see (nearer than MIN_DEPTH_M, or outside its image) keeps all of its
    own. Returns how many anchors left the state."""
    if max_landmarks <= 0 or state.n_landmarks == 0:
        return 0
    keys = state.anchor_keys()
    loads = state.anchor_loads()
    light = (loads >= 1) & (loads <= max_landmarks) & ~state.anchor_pinned() & (keys != key)
    if not light.any():
        return 0
    on = state.anchors_of(np.arange(state.n_landmarks))
    slots = np.flatnonzero(np.isin(on, keys[light]))
    m, M = state.landmarks_nav(slots)
    a_rows = state.anchor_rows(key)
    assert a_rows is not None
    theta, J_m, J_a = AnchoredInverseDepth().from_nav(m, state.x[a_rows], R_cam_body, t_body_cam)
    u = K[0, 0] * theta[:, 0] + K[0, 2]
    v = K[1, 1] * theta[:, 1] + K[1, 2]
    seen = (
        (theta[:, 2] > 0)
        & (theta[:, 2] * MIN_DEPTH_M <= 1.0)
        & (u >= 0)
        & (u <= size_px[0])
        & (v >= 0)
        & (v <= size_px[1])
    )
    bad = np.unique(on[slots[~seen]])
    ok = ~np.isin(on[slots], bad)
    if not ok.any():
        return 0
    before = state.n_anchors
    state.reanchor(slots[ok], key, theta[ok], J_m[ok] @ M[ok], J_a[ok], R_cam_body, t_body_cam)
    return before - state.n_anchors
