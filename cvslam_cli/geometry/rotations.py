"""Rotations: quaternions (x, y, z, w; Hamilton, as ROS and TUM files), matrices, ZYX Euler.

`C_nav_body` is the paper's C^n_b (body -> nav direction cosine matrix); Euler angles are
(roll φ, pitch θ, yaw ψ) applied as yaw-pitch-roll (ZYX), radians.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.records.arrays import F64


def quat_xyzw_to_matrix(q_xyzw: F64) -> F64:
    """(..., 4) unit quaternions (x, y, z, w) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q_xyzw, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape((*q.shape[:-1], 3, 3))


def matrix_to_quat_xyzw(R: F64) -> F64:
    """(..., 3, 3) rotation matrices -> (..., 4) quaternions (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        t = np.trace(m)
        if t > 0:
            s = 2.0 * np.sqrt(t + 1.0)
            q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
        else:
            k = int(np.argmax(np.diag(m)))
            a, b = (k + 1) % 3, (k + 2) % 3
            s = 2.0 * np.sqrt(1.0 + m[k, k] - m[a, a] - m[b, b])
            q = [0.0, 0.0, 0.0, (m[b, a] - m[a, b]) / s]
            q[k] = s / 4
            q[a] = (m[a, k] + m[k, a]) / s
            q[b] = (m[b, k] + m[k, b]) / s
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[i] = -q if q[3] < 0 else q
    return out.reshape((*R.shape[:-2], 4))


def _elementary(roll: float, pitch: float, yaw: float) -> tuple[F64, F64, F64]:
    """Rx(roll), Ry(pitch), Rz(yaw)."""
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    return (
        np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]]),
        np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]]),
        np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]]),
    )


def euler_zyx_to_matrix(roll: float, pitch: float, yaw: float) -> F64:
    """C_nav_body = Rz(yaw) Ry(pitch) Rx(roll) from ZYX Euler angles (paper's C^n_b)."""
    Rx, Ry, Rz = _elementary(roll, pitch, yaw)
    return Rz @ Ry @ Rx


def euler_zyx_derivatives(roll: float, pitch: float, yaw: float) -> F64:
    """(3, 3, 3): d C_nav_body / d (roll, pitch, yaw) for C = Rz(yaw) Ry(pitch) Rx(roll):
    Rz Ry Rx [e1]x, Rz Ry [e2]x Rx, Rz [e3]x Ry Rx."""
    Rx, Ry, Rz = _elementary(roll, pitch, yaw)
    e1x = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    e2x = np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]])
    e3x = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])
    return np.stack([Rz @ Ry @ Rx @ e1x, Rz @ Ry @ e2x @ Rx, Rz @ e3x @ Ry @ Rx])


def euler_zyx_matrices(euler_rad: F64) -> tuple[F64, F64]:
    """Batched `euler_zyx_to_matrix` and `euler_zyx_derivatives`: (k, 3) (roll, pitch, yaw)
    -> C (k, 3, 3) and d C / d (roll, pitch, yaw) (k, 3, 3, 3)."""
    e = np.atleast_2d(np.asarray(euler_rad, dtype=float))
    k = len(e)
    c, s = np.cos(e), np.sin(e)
    # Rx, Ry, Rz (3, k, 3, 3): each a rotation about its axis a, [[c, -s], [s, c]] on the
    # other two axes (i, j) in that order (Ry's, (z, x), gives its -s below the diagonal)
    R = np.zeros((3, k, 3, 3))
    for a, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):
        R[a, :, a, a] = 1.0
        R[a, :, i, i] = R[a, :, j, j] = c[:, a]
        R[a, :, i, j] = -s[:, a]
        R[a, :, j, i] = s[:, a]
    Rx, Ry, Rz = R
    e1x = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    e2x = np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]])
    e3x = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])
    RzRy = Rz @ Ry
    C = RzRy @ Rx
    dC = np.stack([C @ e1x, RzRy @ e2x @ Rx, Rz @ e3x @ Ry @ Rx], axis=1)
    return C, dC


def matrix_to_euler_zyx(C_nav_body: F64) -> F64:
    """(roll, pitch, yaw) of a body -> nav rotation matrix."""
    C = np.asarray(C_nav_body, dtype=float)
    pitch = -np.arcsin(np.clip(C[2, 0], -1.0, 1.0))
    roll = np.arctan2(C[2, 1], C[2, 2])
    yaw = np.arctan2(C[1, 0], C[0, 0])
    return np.array([roll, pitch, yaw])


def so3_log(R: F64) -> F64:
    """(3,) rotation vector (axis times angle, rad) of a rotation matrix R (3, 3); zero for
    angles below 1e-12 rad."""
    angle = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    if not angle > 1e-12:
        return np.zeros(3)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis / (2.0 * np.sin(angle)) * angle


def make_T(R: F64, t: F64) -> F64:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_T(T: F64) -> F64:
    """Inverse of a 4x4 rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def nearest_rotation(R: F64) -> F64:
    """The rotation matrix closest (Frobenius) to an almost-orthonormal (3, 3) matrix `R`
    (SVD, with the sign that makes the determinant +1)."""
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def is_rotation(R: F64, tol: float = 1e-6) -> bool:
    R = np.asarray(R, dtype=float)
    return bool(
        R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=tol) and np.linalg.det(R) > 0
    )


def interpolate_positions(stamps: NDArray, p: F64, at: NDArray) -> F64:
    """(K, 3) positions p (N, 3) given at `stamps` (N,) (increasing; integer nanoseconds or
    seconds) linearly interpolated at `at` (K,) in the same unit; NaN outside the stamps'
    span (no extrapolation). Times are taken relative to the first stamp, so integer
    nanosecond stamps lose no precision."""
    st = np.asarray(stamps)
    at = np.asarray(at)
    out = np.full((len(at), 3), np.nan)
    if len(st) == 0:
        return out
    ok = (at >= st[0]) & (at <= st[-1])
    if not ok.any():
        return out
    t = (st - st[0]).astype(float)
    ta = (at[ok] - st[0]).astype(float)
    for k in range(3):
        out[ok, k] = np.interp(ta, t, p[:, k])
    return out


def interpolate_poses(
    stamps_ns: NDArray[np.int64], p: F64, q_xyzw: F64, at_ns: NDArray[np.int64]
) -> tuple[F64, F64, NDArray[np.bool_]]:
    """Poses of a trajectory (stamps (N,) increasing, positions (N, 3), quaternions (N, 4))
    at stamps `at_ns` (K,): positions interpolated linearly, rotations by slerp. Returns
    positions (K, 3), rotation matrices (K, 3, 3) and which stamps lie inside the
    trajectory's span (the others are NaN)."""
    from scipy.spatial.transform import Rotation, Slerp

    at = np.asarray(at_ns, dtype=np.int64)
    st = np.asarray(stamps_ns, dtype=np.int64)
    out_p = interpolate_positions(st, p, at)
    out_R = np.full((len(at), 3, 3), np.nan)
    if len(st) == 0:
        return out_p, out_R, np.zeros(len(at), bool)
    ok = (at >= st[0]) & (at <= st[-1])
    if not ok.any():
        return out_p, out_R, ok
    t = (st - st[0]).astype(float)
    ta = (at[ok] - st[0]).astype(float)
    rots = Rotation.from_quat(np.asarray(q_xyzw, dtype=float))
    if len(st) == 1:
        out_R[ok] = rots.as_matrix()[0]
    else:
        out_R[ok] = Slerp(t, rots)(ta).as_matrix()
    return out_p, out_R, ok
