"""Data association: which stereo matches of a frame are re-observations of mapped landmarks.

The stereo constraint of extract, applied over time: every landmark in the state is predicted
into both images with the observation model (eq. 19) and its innovation covariance

    S_j = H_j P H_j^T + R,     H_j = [H_v,j  H_m,j]  (the vehicle block and landmark j only)

and a stereo match z_i (u_l, v_l, u_r, v_r) is a candidate for landmark j only inside that
landmark's innovation window, the chi-square gate d2_ij = (z_i - z_j)^T S_j^-1 (z_i - z_j) <
chi2_4(p). Among its candidates a landmark takes the one with the smallest descriptor
distance D1, if D1 < ratio * D2 (second smallest in the window) and D1 < max_distance; a match
claimed by several landmarks goes to the smallest D1. Everything is vectorised over
landmarks x matches (a frame has ~100 landmarks in view and a few hundred matches).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True, eq=False)
class LandmarkPrediction:
    """k landmarks predicted into a stereo frame: `slots` (k,), `z` (k, 4) predicted pixels
    (u_l, v_l, u_r, v_r), `H_v` (k, 4, n_v) w.r.t. the vehicle block, `H_m` (k, 4, 3)
    w.r.t. the landmark, `S` (k, 4, 4) innovation covariances."""

    slots: I64
    z: F64
    H_v: F64
    H_m: F64
    S: F64


@dataclass(frozen=True, eq=False)
class Association:
    """a accepted pairs: `pred_index` (a,) rows of the prediction, `match_index` (a,) rows of
    the frame's matches, `d2` (a,) Mahalanobis distances, `descriptor_distance` (a,);
    `near_landmark` (M,) bool: the match lies inside some landmark's window (accepted or not),
    so it must not start a new landmark (it would duplicate one)."""

    pred_index: I64
    match_index: I64
    d2: F64
    descriptor_distance: F64
    near_landmark: NDArray[np.bool_]


def camera_depths(obs: StereoObservationModel, p_nav_m: F64, euler_rad: F64, m_nav_m: F64) -> F64:
    """(N,) depth of landmarks m (N, 3) in the left camera."""
    C = euler_zyx_to_matrix(*euler_rad)
    q = (np.atleast_2d(m_nav_m) - p_nav_m) @ C
    return (q - obs.t_body_cam[0]) @ obs.R_cam_body[0][2]


def predict_landmarks(
    obs: StereoObservationModel,
    p_nav_m: F64,
    euler_rad: F64,
    J_pose: F64,
    slots: I64,
    m_nav_m: F64,
    P_vv: F64,
    P_vm: F64,
    P_mm: F64,
    R: F64,
) -> LandmarkPrediction:
    """Predict landmarks m (k, 3) seen from pose (p, Psi), whose d(p, Psi)/d x_v is J_pose
    (6, n_v). P_vv (n_v, n_v), P_vm (k, n_v, 3), P_mm (k, 3, 3): covariance blocks."""
    z, H_pose, H_m = obs.predict(p_nav_m, euler_rad, m_nav_m)
    H_v = H_pose @ J_pose
    HvPvm = H_v @ P_vm  # (k, 4, 3)
    cross = HvPvm @ np.swapaxes(H_m, 1, 2)
    S = (
        H_v @ P_vv @ np.swapaxes(H_v, 1, 2)
        + cross
        + np.swapaxes(cross, 1, 2)
        + H_m @ P_mm @ np.swapaxes(H_m, 1, 2)
        + R
    )
    return LandmarkPrediction(np.asarray(slots, dtype=np.int64), z, H_v, H_m, S)


def in_view(z: F64, depth_m: F64, size_px: NDArray[np.int64], margin_px: float = 0.0) -> NDArray:
    """(k,) bool: in front of the camera and inside both images (size_px (2, 2) width,
    height of left and right)."""
    ok = depth_m > 0
    for c in range(2):
        u, v = z[:, 2 * c], z[:, 2 * c + 1]
        w, h = size_px[c]
        ok &= (u >= -margin_px) & (u < w + margin_px) & (v >= -margin_px) & (v < h + margin_px)
    return ok


def descriptor_distances(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.float32]:
    """(k, M) Euclidean distances between descriptors a (k, D) and b (M, D)."""
    af = a.astype(np.float32)
    bf = b.astype(np.float32)
    d2 = (af * af).sum(1)[:, None] + (bf * bf).sum(1)[None, :] - 2.0 * (af @ bf.T)
    return np.sqrt(np.maximum(d2, 0.0))


def associate(
    pred: LandmarkPrediction,
    landmark_desc: NDArray[np.uint8],
    z_obs: F64,
    obs_desc: NDArray[np.uint8],
    gate_chi2: float,
    ratio: float,
    max_distance: float,
) -> Association:
    """Match predicted landmarks (k) with a frame's stereo matches z_obs (M, 4) (module
    docstring)."""
    k, M = len(pred.z), len(z_obs)
    if k == 0 or M == 0:
        e = np.zeros(0, dtype=np.int64)
        return Association(e, e, np.zeros(0), np.zeros(0), np.zeros(M, dtype=bool))
    S_inv = np.linalg.inv(pred.S)
    diff = z_obs[None, :, :] - pred.z[:, None, :]  # (k, M, 4)
    d2 = np.sum((diff @ S_inv) * diff, axis=2)  # (k, M); S_inv symmetric
    gated = d2 < gate_chi2
    near = gated.any(axis=0)
    rows = np.flatnonzero(gated.any(axis=1))
    if len(rows) == 0:
        e = np.zeros(0, dtype=np.int64)
        return Association(e, e, np.zeros(0), np.zeros(0), near)
    cols = np.flatnonzero(near)
    D = descriptor_distances(landmark_desc[rows], obs_desc[cols])
    D = np.where(gated[np.ix_(rows, cols)], D, np.inf)
    best = np.argmin(D, axis=1)
    best_d = D[np.arange(len(rows)), best]
    second_d = np.partition(D, 1, axis=1)[:, 1] if D.shape[1] >= 2 else np.full(len(rows), np.inf)
    ok = (best_d < max_distance) & (best_d < ratio * second_d)
    lm = rows[ok]
    mi = cols[best[ok]]
    dd = best_d[ok].astype(float)
    # one landmark per match: the smallest descriptor distance wins
    order = np.argsort(dd, kind="stable")
    _, first = np.unique(mi[order], return_index=True)
    keep = order[first]
    keep.sort()
    return Association(lm[keep], mi[keep], d2[lm[keep], mi[keep]], dd[keep], near)


def spread_order(uv_px: F64, priority: F64, size_px: tuple[int, int], grid: int = 4) -> I64:
    """Order points for selection so that the first ones cover the image: a `grid` x `grid`
    bucketing, round-robin over buckets, each bucket in increasing `priority` (lower first).
    Returns indices into uv_px (N, 2)."""
    n = len(uv_px)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    w, h = size_px
    bx = np.clip((uv_px[:, 0] * grid / max(w, 1)).astype(np.int64), 0, grid - 1)
    by = np.clip((uv_px[:, 1] * grid / max(h, 1)).astype(np.int64), 0, grid - 1)
    bucket = by * grid + bx
    order = np.lexsort((priority, bucket))
    b_sorted = bucket[order]
    starts = np.flatnonzero(np.r_[True, b_sorted[1:] != b_sorted[:-1]])
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    return order[np.lexsort((priority[order], rank))]


def pose_consistent(
    pred: LandmarkPrediction,
    rows: I64,
    z_obs: F64,
    P_vv: F64,
    P_mm: F64,
    R: F64,
    gate_chi2: float,
    iterations: int = 3,
) -> NDArray[np.bool_]:
    """Which associations (prediction rows `rows`, observations z_obs (a, 4)) agree with one
    common vehicle correction. Individually gated innovations can still be wrong matches:
    the windows are wide while the pose is uncertain, and a repetitive texture offers a
    look-alike inside them. The innovations of right matches are explained by one small
    correction dx of the vehicle state, nu_j = H_v,j dx + (landmark and pixel noise with
    covariance W_j^-1 = H_m,j P_mm,j H_m,j^T + R); dx is the weighted least-squares solution
    with the prior P_vv, and a match whose residual nu_j - H_v,j dx fails the chi-square gate
    is dropped, re-solving without it (`iterations` times). P_mm (a, 3, 3)."""
    a = len(rows)
    keep = np.ones(a, dtype=bool)
    if a == 0:
        return keep
    H_v = pred.H_v[rows]
    H_m = pred.H_m[rows]
    nu = z_obs - pred.z[rows]
    W = np.linalg.inv(H_m @ P_mm @ np.swapaxes(H_m, 1, 2) + R)  # (a, 4, 4)
    HtW = np.swapaxes(H_v, 1, 2) @ W  # (a, n_v, 4)
    info_prior = np.linalg.inv(P_vv)
    for _ in range(iterations):
        A = info_prior + np.sum(HtW[keep] @ H_v[keep], axis=0)
        b = np.sum(HtW[keep] @ nu[keep][:, :, None], axis=0)[:, 0]
        dx = np.linalg.solve(A, b)
        r = nu - H_v @ dx
        d2 = np.sum((r[:, None, :] @ W)[:, 0] * r, axis=1)
        new_keep = d2 < gate_chi2
        if np.array_equal(new_keep, keep) or not new_keep.any():
            break
        keep = new_keep
    return keep
