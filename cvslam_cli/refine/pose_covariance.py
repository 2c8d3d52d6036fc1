"""Pose covariances between GTSAM's Pose3 tangent space and cvslam's (p, Psi) convention.

GTSAM perturbs a pose on the right, T' = T Exp([dw; dt]) (rotation first, both in the body
frame), so to first order p' = p + R dt and R' = R Exp(dw). cvslam's pose covariances
(docs/fuse_outputs.md) are over (p (nav, m), Psi = roll, pitch, yaw (ZYX, rad)); with
Psi_dot = E(Psi) w for body rates w (`motion.ins.euler_rate_matrix`), dPsi = E dw:

    [dp; dPsi] = J [dw; dt],   J = [[0, R], [E, 0]],   Sigma_(p,Psi) = J Sigma_tangent J^T.
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.motion.ins import euler_rate_matrix
from cvslam_cli.geometry.rotations import matrix_to_euler_zyx
from cvslam_cli.records.arrays import F64


def tangent_to_pose_jacobian(T_nav_body: F64) -> F64:
    """J (6, 6) = d(p, Psi) / d(dw, dt) at the pose T_nav_body (4, 4)."""
    R = T_nav_body[:3, :3]
    E, _ = euler_rate_matrix(matrix_to_euler_zyx(R))
    J = np.zeros((6, 6))
    J[0:3, 3:6] = R
    J[3:6, 0:3] = E
    return J


def pose_cov_from_tangent(T_nav_body: F64, cov_tangent: F64) -> F64:
    """(6, 6) covariance of (p, Psi) from GTSAM's marginal covariance of the pose."""
    J = tangent_to_pose_jacobian(T_nav_body)
    out = J @ cov_tangent @ J.T
    return 0.5 * (out + out.T)


def tangent_cov_from_pose(T_nav_body: F64, cov_pose: F64) -> F64:
    """(6, 6) covariance in GTSAM's tangent space from one of (p, Psi) (for a prior)."""
    Jinv = np.linalg.inv(tangent_to_pose_jacobian(T_nav_body))
    out = Jinv @ cov_pose @ Jinv.T
    return 0.5 * (out + out.T)
