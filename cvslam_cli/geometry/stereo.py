"""Stereo triangulation (the inverse observation model) with its covariance.

Points are triangulated from the two 3x4 projection matrices of the rig expressed in the
LEFT camera frame (M_left = K_l [I | 0], M_right = K_r [R_rl | t_rl]) and undistorted pixel
coordinates: the point whose projections are nearest the four pixel coordinates (least
squares in pixels, the maximum-likelihood point for independent Gaussian pixel noise), found
by Gauss-Newton from the linear (DLT) solution. The DLT, exact for noise-free data on any
rig, minimises an algebraic error instead: its equations are the pixel errors times each
point's depth, so a row disagreement v_l != v_r (noise) is cheapest to explain by moving the
point closer, and its inverse depth comes out biased high by ~(sigma_v / disparity)^2, every
point alike (1.1 % at 100 m with a 1.5 m baseline, fx 450 and 0.5 px noise). In the left
camera's inverse-depth coordinates (alpha, beta, rho) = (x / z, y / z, 1 / z) both
projections are ratios of functions linear in them, so Gauss-Newton there is well
conditioned up to infinity (rho = 0), and for a rectified rig the projections are linear:
alpha and rho then follow from u_l and the disparity, beta from the mean of the two rows,
in one step. The covariance is the least-squares point's: isotropic pixel noise through
the projections' Jacobian (eq. 19 inverted).
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


# Gauss-Newton steps of `triangulate` from the DLT point (one suffices for a rectified rig)
REFINE_STEPS = 3


def triangulate(M_left: F64, M_right: F64, uv_left: F64, uv_right: F64) -> F64:
    """(N, 2) + (N, 2) undistorted pixels -> (N, 3) points in the left camera frame: the
    least-squares point in pixels (module docstring), Gauss-Newton in the left camera's
    (alpha, beta, rho) from the DLT point; a point the DLT puts at the left camera's centre
    plane (no inverse depth), or whose steps do not stay finite, stays as the DLT has it."""
    uv_l = np.asarray(uv_left, dtype=float).reshape(-1, 2)
    uv_r = np.asarray(uv_right, dtype=float).reshape(-1, 2)
    X = _triangulate_dlt(M_left, M_right, uv_l, uv_r)
    ok = np.abs(X[:, 2]) > 1e-12
    if not ok.any():
        return X
    theta = _inverse_depth(X[ok])
    uv = np.concatenate([uv_l[ok], uv_r[ok]], axis=1)  # (n, 4)
    for _ in range(REFINE_STEPS):
        r, J = _reprojection(M_left, M_right, theta, uv)
        JtJ = np.einsum("nki,nkj->nij", J, J)
        Jtr = np.einsum("nki,nk->ni", J, r)
        theta = theta - _solve(JtJ, Jtr)
    out = X.copy()
    rho = theta[:, 2]
    good = np.isfinite(theta).all(axis=1) & (np.abs(rho) > 1e-12)
    idx = np.flatnonzero(ok)[good]
    out[idx] = (
        np.stack([theta[good, 0], theta[good, 1], np.ones(good.sum())], axis=1) / rho[good, None]
    )
    return out


def _inverse_depth(X: F64) -> F64:
    """(n, 3) points in the left camera -> their (alpha, beta, rho) = (x / z, y / z, 1 / z)."""
    z = X[:, 2]
    return np.stack([X[:, 0] / z, X[:, 1] / z, 1.0 / z], axis=1)


def _reprojection(M_left: F64, M_right: F64, theta: F64, uv: F64) -> tuple[F64, F64]:
    """Residuals r (n, 4) (projections minus pixels, left then right) of points theta (n, 3)
    = (alpha, beta, rho) in the left camera, and d r / d theta (n, 4, 3): a camera M (3, 4)
    sees w = M[:, :3] (alpha, beta, 1) + M[:, 3] rho at (w_0, w_1) / w_2."""
    ray = np.stack([theta[:, 0], theta[:, 1], np.ones(len(theta))], axis=1)
    r = np.empty((len(theta), 4))
    J = np.empty((len(theta), 4, 3))
    for c, M in enumerate((M_left, M_right)):
        w = ray @ M[:, :3].T + theta[:, 2:3] * M[:, 3]
        dw = np.stack([M[:, 0], M[:, 1], M[:, 3]], axis=1)  # (3, 3): d w / d theta
        r[:, 2 * c : 2 * c + 2] = w[:, :2] / w[:, 2:3] - uv[:, 2 * c : 2 * c + 2]
        # d (w_0 / w_2, w_1 / w_2) / d w, then through dw
        inv = 1.0 / w[:, 2]
        D = np.zeros((len(theta), 2, 3))
        D[:, 0, 0] = D[:, 1, 1] = inv
        D[:, :, 2] = -w[:, :2] * (inv**2)[:, None]
        J[:, 2 * c : 2 * c + 2] = D @ dw
    return r, J


def _triangulate_dlt(M_left: F64, M_right: F64, uv_l: F64, uv_r: F64) -> F64:
    """(N, 3) the linear (DLT) points of (N, 2) + (N, 2) pixels (module docstring)."""
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
    return _solve(AtA, Atb)


def _solve(A: F64, b: F64 | None = None) -> F64:
    """x (n, 3) with A x = b for (n, 3, 3) and (n, 3), or A^-1 (n, 3, 3) without b; where some
    A is singular (a point at infinity: equal pixels on a rectified rig) the least-norm
    solutions (pseudo-inverse): no error for the points that callers drop."""
    try:
        return np.linalg.inv(A) if b is None else np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        A_inv = np.linalg.pinv(A)
        return A_inv if b is None else np.einsum("nij,nj->ni", A_inv, b)


def triangulation_covariance(
    M_left: F64,
    M_right: F64,
    uv_left: F64,
    uv_right: F64,
    sigma_px: float | F64,
    p_cam_m: F64 | None = None,
) -> F64:
    """(N, 3, 3) covariance of `triangulate` for independent N(0, sigma_px^2) pixel noise on
    each of the four coordinates (`sigma_px` scalar or one per point), points in front of the
    left camera: the least-squares point's first-order covariance sigma^2 (J^T J)^-1 in
    (alpha, beta, rho) (J (4, 3): the projections' Jacobian there; exact for a rectified rig,
    whose projections are linear in them), mapped to the point by d X / d (alpha, beta, rho).
    `p_cam_m` (N, 3): the points `triangulate` gave for these pixels, when the caller has
    them (else triangulated here)."""
    X = triangulate(M_left, M_right, uv_left, uv_right) if p_cam_m is None else p_cam_m
    uv = np.concatenate(
        [np.asarray(uv_left, dtype=float).reshape(-1, 2),
         np.asarray(uv_right, dtype=float).reshape(-1, 2)], axis=1,
    )  # fmt: skip
    z = X[:, 2]
    _, J = _reprojection(M_left, M_right, _inverse_depth(X), uv)
    JtJ = np.einsum("nki,nkj->nij", J, J)
    cov_theta = _solve(JtJ)
    D = np.zeros((len(X), 3, 3))  # d X / d theta, X = (alpha, beta, 1) / rho
    D[:, 0, 0] = D[:, 1, 1] = z
    D[:, :, 2] = -X * z[:, None]
    var = np.broadcast_to(np.asarray(sigma_px, dtype=float) ** 2, (len(X),))
    return D @ cov_theta @ np.swapaxes(D, 1, 2) * var[:, None, None]


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
    cov = triangulation_covariance(M_l, M_r, ul[keep], ur[keep], sigma_px, p_cam[keep])
    return p_cam, cov, keep
