"""The stereo observation model (paper eq. 19) with analytic Jacobians, and its inverse.

A landmark m (nav frame, NED) seen by a vehicle at position p (nav) with Euler angles
Psi = (roll, pitch, yaw) (ZYX, C_nav_body = Rz(yaw) Ry(pitch) Rx(roll)) gives four numbers,
its ideal (undistorted) pixel in the left and the right image:

    q      = C_nav_body^T (m - p)                  the landmark in the body frame
    p_c    = R_cam_body (q - t_body_cam)           ... in camera c's optical frame
    (u, v) = (fx x / z + cx, fy y / z + cy)        eq. 19: M^c [m; 1] with M^c = K_c [R | t]

Jacobians (vectorised over landmarks):
    d p_c / d m   = R_cam_body C^T =: A            d p_c / d p = -A
    d q / d Psi_k = (d C / d Psi_k)^T (m - p)      (`rotations.euler_zyx_derivatives`)
    d (u, v) / d p_c = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]

A rectified rig (`StereoObservationModel.rectified`: both cameras with the same rotation,
focal length fy and row centre cy, the baseline along the cameras' x axis) predicts v_l = v_r
for every landmark, so the two v rows of H are one row: with independent pixel noise sigma^2
per coordinate their mean v = (v_l + v_r) / 2, of noise sigma^2 / 2, carries all they say
about the state, and the difference v_l - v_r (noise 2 sigma^2) none. `mean_v_rows` maps an
observation's four rows to those three (u_l, v, u_r): the update is the same to rounding (the
information H^T R^-1 H and H^T R^-1 (y - h) are unchanged) with a quarter fewer rows.

The inverse model turns a point triangulated in the left camera frame (extract's
`match_p_cam_m`, covariance `match_cov_cam_m2`) into a nav-frame landmark with a covariance
that includes the vehicle's pose uncertainty (Jacobians w.r.t. the point and the pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.geometry.rotations import euler_zyx_derivatives, euler_zyx_to_matrix
from cvslam_cli.records.arrays import F64


def _pixels(K: F64, p_cam_m: F64) -> tuple[F64, F64]:
    """(u, v) (N,) of points p_cam_m (N, 3) in a camera with intrinsics K (3, 3) (eq. 19)."""
    x, y, zc = p_cam_m[:, 0], p_cam_m[:, 1], p_cam_m[:, 2]
    return K[0, 0] * x / zc + K[0, 1] * y / zc + K[0, 2], K[1, 1] * y / zc + K[1, 2]


@dataclass(frozen=True, eq=False)
class StereoObservationModel:
    """Left/right cameras: K (2, 3, 3), R_cam_body (2, 3, 3), t_body_cam (2, 3) (camera
    centres in the body frame)."""

    K: F64
    R_cam_body: F64
    t_body_cam: F64

    @classmethod
    def from_rig(cls, rig: StereoRig) -> StereoObservationModel:
        cams = (rig.left, rig.right)
        return cls(
            K=np.stack([c.K for c in cams]),
            R_cam_body=np.stack([c.T_body_cam[:3, :3].T for c in cams]),
            t_body_cam=np.stack([c.T_body_cam[:3, 3] for c in cams]),
        )

    @cached_property
    def rectified(self) -> bool:
        """Whether v_l = v_r for every point (module docstring): equal rotations, equal
        second rows of K (fy, cy; no skew in v) and a baseline along the cameras' x axis, to
        1e-9 relative (a calibration's rounding)."""
        K_l, K_r = self.K
        R_l, R_r = self.R_cam_body
        b_cam = R_l @ (self.t_body_cam[1] - self.t_body_cam[0])  # baseline in the left camera
        tol = 1e-9
        return bool(
            np.allclose(R_l, R_r, rtol=0.0, atol=tol)
            and np.allclose(K_l[1], K_r[1], rtol=tol, atol=0.0)
            and abs(K_l[1, 0]) <= tol * abs(K_l[1, 1])
            and np.all(np.abs(b_cam[1:]) <= tol * np.linalg.norm(b_cam))
        )

    def with_right_cx(self, du_px: float) -> StereoObservationModel:
        """The model with the right camera's principal point u0 moved by du_px (a correction
        estimated by the filter, `rig_calibration.py`): it predicts u_r + du_px."""
        if du_px == 0.0:
            return self
        K = self.K.copy()
        K[1, 0, 2] += du_px
        return StereoObservationModel(K, self.R_cam_body, self.t_body_cam)

    @cached_property
    def fx_baseline(self) -> float:
        """fx b (px m) of a rectified rig: a point's depth is fx b / disparity."""
        return float(self.K[0, 0, 0] * np.linalg.norm(self.t_body_cam[1] - self.t_body_cam[0]))

    def project(self, p_nav_m: F64, euler_rad: F64, m_nav_m: F64) -> F64:
        """(N, 3) landmarks seen from pose (p, Psi) -> z (N, 4) = (u_l, v_l, u_r, v_r): the
        pixels of `predict` without its Jacobians (the same arithmetic, bit for bit), for
        the visibility tests that read only where a point falls."""
        C = euler_zyx_to_matrix(*euler_rad)
        w = np.atleast_2d(np.asarray(m_nav_m, dtype=float)) - np.asarray(p_nav_m, dtype=float)
        q = w @ C
        z = np.empty((w.shape[0], 4))
        for c in range(2):
            pc = (q - self.t_body_cam[c]) @ self.R_cam_body[c].T
            z[:, 2 * c], z[:, 2 * c + 1] = _pixels(self.K[c], pc)
        return z

    def predict(self, p_nav_m: F64, euler_rad: F64, m_nav_m: F64) -> tuple[F64, F64, F64]:
        """(N, 3) landmarks seen from pose (p, Psi) -> z (N, 4) = (u_l, v_l, u_r, v_r),
        H_pose (N, 4, 6) w.r.t. (p, Psi), H_m (N, 4, 3) w.r.t. the landmark (eq. 19)."""
        C = euler_zyx_to_matrix(*euler_rad)  # C_nav_body
        D = euler_zyx_derivatives(*euler_rad)  # d C / d (roll, pitch, yaw)
        w = np.atleast_2d(np.asarray(m_nav_m, dtype=float)) - np.asarray(p_nav_m, dtype=float)
        q = w @ C  # C^T w per row
        dq = np.stack([w @ D[k] for k in range(3)], axis=2)  # (N, 3, 3): d q / d Psi
        n = w.shape[0]
        z = np.empty((n, 4))
        H_pose = np.empty((n, 4, 6))
        H_m = np.empty((n, 4, 3))
        for c in range(2):
            R = self.R_cam_body[c]
            pc = (q - self.t_body_cam[c]) @ R.T
            x, y, zc = pc[:, 0], pc[:, 1], pc[:, 2]
            K = self.K[c]
            z[:, 2 * c], z[:, 2 * c + 1] = _pixels(K, pc)
            J = np.zeros((n, 2, 3))
            J[:, 0, 0] = K[0, 0] / zc
            J[:, 0, 1] = K[0, 1] / zc
            J[:, 0, 2] = -(K[0, 0] * x + K[0, 1] * y) / zc**2
            J[:, 1, 1] = K[1, 1] / zc
            J[:, 1, 2] = -K[1, 1] * y / zc**2
            A = R @ C.T  # d p_c / d m
            JA = J @ A
            H_m[:, 2 * c : 2 * c + 2] = JA
            H_pose[:, 2 * c : 2 * c + 2, :3] = -JA
            H_pose[:, 2 * c : 2 * c + 2, 3:] = J @ (R @ dq)
        return z, H_pose, H_m

    def left_camera_centre(self, p_nav_m: F64, euler_rad: F64) -> F64:
        """(3,) the left camera's centre in nav at pose (p, Psi)."""
        return (
            np.asarray(p_nav_m, dtype=float) + euler_zyx_to_matrix(*euler_rad) @ self.t_body_cam[0]
        )

    def landmark_jacobians(
        self, p_nav_m: F64, euler_rad: F64, p_cam_m: F64
    ) -> tuple[F64, F64, F64]:
        """Inverse model m = p + C (R_cam_body^T p_c + t_body_cam) for (N, 3) points in the
        LEFT camera frame: m (N, 3), d m / d (p, Psi) (N, 3, 6), d m / d p_c (3, 3)."""
        C = euler_zyx_to_matrix(*euler_rad)
        b = np.atleast_2d(p_cam_m) @ self.R_cam_body[0] + self.t_body_cam[0]  # body frame
        m = b @ C.T + np.asarray(p_nav_m, dtype=float)
        D = euler_zyx_derivatives(*euler_rad)
        J_pose = np.empty((len(b), 3, 6))
        J_pose[:, :, :3] = np.eye(3)
        J_pose[:, :, 3:] = np.stack([b @ D[k].T for k in range(3)], axis=2)  # d (C b) / d Psi
        return m, J_pose, C @ self.R_cam_body[0].T

    def landmark_from_camera_point(
        self,
        p_nav_m: F64,
        euler_rad: F64,
        p_cam_m: F64,
        cov_cam_m2: F64,
        cov_pose: F64 | None = None,
    ) -> tuple[F64, F64]:
        """Inverse model: (N, 3) points in the LEFT camera frame with (N, 3, 3) covariances,
        seen from pose (p, Psi) with (6, 6) covariance `cov_pose` of (p, Psi) (None: exact
        pose) -> (N, 3) nav-frame landmarks and (N, 3, 3) covariances
        m = p + C (R_cam_body^T p_c + t_body_cam)."""
        m, J_pose, J_pc = self.landmark_jacobians(p_nav_m, euler_rad, p_cam_m)
        cov = J_pc @ np.asarray(cov_cam_m2) @ J_pc.T
        if cov_pose is not None:
            cov = cov + J_pose @ np.asarray(cov_pose) @ np.swapaxes(J_pose, 1, 2)
        return m, cov


# (u_l, v_l, u_r, v_r) -> (u_l, (v_l + v_r) / 2, u_r): the rows of a rectified rig's
# observation that carry information (module docstring)
MEAN_V_ROWS = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.5, 0.0, 0.5], [0.0, 0.0, 1.0, 0.0]])
# The covariance of (u_l, v_l, u_r, v_r) that is the bearing's, for unit noise per coordinate:
# the bearing ((u_l + u_r) / 2, (v_l + v_r) / 2) of independent unit noise has variance 1/2 and
# moves both images' keypoints alike; the disparity u_l - u_r and v_l - v_r are the rest.
BEARING_ROWS = 0.5 * np.array(
    [[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0], [1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]]
)


def mean_v_rows(a: F64) -> F64:
    """(k, 4, ...) rows per observation (u_l, v_l, u_r, v_r) -> (k, 3, ...) (u_l, v, u_r)
    with v the mean of v_l and v_r (`MEAN_V_ROWS`)."""
    out = a[:, :3].copy()
    out[:, 1] = 0.5 * (a[:, 1] + a[:, 3])
    return out


@dataclass(frozen=True)
class RightCxShift:
    """Stereo points of a rectified rig, triangulated with its calibrated right principal
    point, moved to the rig whose right u0 is off by `du_px` (`rig_calibration.py`): the
    disparity d = fx b / z becomes d + du, so a point p (left camera frame) scales to
    p' = s p with s = fx b / (fx b + du z), along its left ray. `fx_baseline` fx b (px m)."""

    fx_baseline: float
    du_px: float

    def apply(self, p_cam_m: F64, cov_cam_m2: F64) -> tuple[F64, F64, F64]:
        """Points (M, 3) and covariances (M, 3, 3) -> the moved points p', their covariances
        J C J^T (J = dp'/dp = s I + p ds/dz e_z^T) and dp'/du (M, 3) = -p' z' / (fx b)."""
        fb, du = self.fx_baseline, self.du_px
        z = p_cam_m[:, 2]
        denom = fb + du * z
        s = fb / denom
        p_new = p_cam_m * s[:, None]
        J = s[:, None, None] * np.eye(3)
        J[:, :, 2] += p_cam_m * (-fb * du / denom**2)[:, None]
        cov_new = J @ cov_cam_m2 @ np.swapaxes(J, 1, 2)
        dp_du = -p_new * (p_new[:, 2] / fb)[:, None]
        return p_new, 0.5 * (cov_new + np.swapaxes(cov_new, 1, 2)), dp_du
