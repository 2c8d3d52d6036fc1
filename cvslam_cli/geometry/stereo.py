"""Stereo triangulation (the inverse observation model) with its covariance.

Points are triangulated from the two 3x4 projection matrices of the rig expressed in the
LEFT camera frame (M_left = K_l [I | 0], M_right = K_r [R_rl | t_rl]) and undistorted pixel
coordinates, by the linear (DLT) method, which is exact for noise-free data on any rig,
rectified or not. The covariance maps isotropic pixel noise through the Jacobian of the
triangulation with respect to the four pixel coordinates (eq. 19 inverted).
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.geometry.rotations import invert_T
from cvslam_cli.records.arrays import F64


def projection_matrices(rig: StereoRig) -> tuple[F64, F64]:
    """(M_left, M_right), each (3, 4), mapping LEFT-camera-frame points to undistorted pixels."""
    M_left = rig.left.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    T_right_left = invert_T(rig.T_left_right)
    M_right = rig.right.K @ T_right_left[:3, :]
    return M_left, M_right


def triangulate(M_left: F64, M_right: F64, uv_left: F64, uv_right: F64) -> F64:
    """(N, 2) + (N, 2) undistorted pixels -> (N, 3) points in the left camera frame (DLT)."""
    uv_l = np.asarray(uv_left, dtype=float).reshape(-1, 2)
    uv_r = np.asarray(uv_right, dtype=float).reshape(-1, 2)
    A = np.stack(
        [
            uv_l[:, 0:1] * M_left[2] - M_left[0],
            uv_l[:, 1:2] * M_left[2] - M_left[1],
            uv_r[:, 0:1] * M_right[2] - M_right[0],
            uv_r[:, 1:2] * M_right[2] - M_right[1],
        ],
        axis=1,
    )  # (N, 4, 4)
    # least squares on [X; 1]: minimise |A[:, :, :3] X + A[:, :, 3]|
    Ax, b = A[:, :, :3], -A[:, :, 3]
    AtA = np.einsum("nij,nik->njk", Ax, Ax)
    Atb = np.einsum("nij,ni->nj", Ax, b)
    return np.linalg.solve(AtA, Atb[..., None])[..., 0]


def triangulation_covariance(
    M_left: F64, M_right: F64, uv_left: F64, uv_right: F64, sigma_px: float | F64
) -> F64:
    """(N, 3, 3) covariance of `triangulate` for independent N(0, sigma_px^2) pixel noise on
    each of the four coordinates (`sigma_px` scalar or one per point): J J^T sigma^2 with
    J = d point / d (u_l, v_l, u_r, v_r) (central differences of the exact triangulation,
    step 1e-3 px)."""
    uv_l = np.asarray(uv_left, dtype=float).reshape(-1, 2)
    uv_r = np.asarray(uv_right, dtype=float).reshape(-1, 2)
    h = 1e-3
    J = np.empty((uv_l.shape[0], 3, 4))
    for k in range(4):
        d = np.zeros(4)
        d[k] = h
        plus = triangulate(M_left, M_right, uv_l + d[:2], uv_r + d[2:])
        minus = triangulate(M_left, M_right, uv_l - d[:2], uv_r - d[2:])
        J[:, :, k] = (plus - minus) / (2 * h)
    var = np.broadcast_to(np.asarray(sigma_px, dtype=float) ** 2, (uv_l.shape[0],))
    return np.einsum("nik,njk->nij", J, J) * var[:, None, None]


def triangulate_matches(
    rig: StereoRig, uv_left: F64, uv_right: F64, max_range_m: float, sigma_px: float
) -> tuple[F64, F64, np.ndarray]:
    """(p_cam (N, 3), cov (K, 3, 3) of the kept points, keep (N,) bool) of matched
    undistorted pixels: a point is kept in front of both cameras and within `max_range_m`
    of the left one."""
    M_l, M_r = projection_matrices(rig)
    ul = np.asarray(uv_left, dtype=float).reshape(-1, 2)
    ur = np.asarray(uv_right, dtype=float).reshape(-1, 2)
    p_cam = triangulate(M_l, M_r, ul, ur) if len(ul) else np.zeros((0, 3))
    T_rl = np.linalg.inv(rig.T_left_right)
    z_right = p_cam @ T_rl[2, :3] + T_rl[2, 3]
    keep = (p_cam[:, 2] > 0) & (z_right > 0) & (np.linalg.norm(p_cam, axis=1) <= max_range_m)
    return p_cam, triangulation_covariance(M_l, M_r, ul[keep], ur[keep], sigma_px), keep
