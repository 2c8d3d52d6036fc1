"""Motion factors between consecutive keyframes of one vehicle, from the filter's motion
model and the same motion pieces (each driven by the samples at its midpoint, as the filter
steps: `motion_segments`):

- IMU (`InsModel`): GTSAM's combined preintegration (Forster et al.), pose, nav-frame
  velocity and IMU biases of both keyframes, with the model's white-noise densities and
  bias random walks; gravity g_nav (NED: +z down) as the filter's;
- wheel odometry (`OdometryModel`): the relative pose the odometry integrates to, with
  the covariance the model propagates (x, y, yaw), the height, roll and pitch held by
  `planar_sigma` (the 3-DOF model fixes them);
- constant velocity (`ConstantVelocityModel`, no motion sensor): the model's white
  acceleration as a prior on consecutive (position, nav velocity) and (attitude, body rate)
  pairs: e = [p_j - p_i - v_i dt; v_j - v_i] with covariance
  q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (per axis), the same for Log(R_i^T R_j) - w_i dt.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from cvslam_cli.estimation.motion.models import (
    ConstantVelocityModel,
    InsModel,
    OdometryModel,
    propagate,
)
from cvslam_cli.records.arrays import F64

TINY_VARIANCE = 1e-12  # a zero random walk or integration noise, kept positive definite


def imu_params(model: InsModel) -> gtsam.PreintegrationCombinedParams:
    """Preintegration parameters of the filter's IMU model (densities squared: GTSAM's
    continuous-time covariances)."""
    z = model.noise
    p = gtsam.PreintegrationCombinedParams(np.asarray(model.g_nav, dtype=float))
    eye = np.eye(3)
    p.setAccelerometerCovariance(eye * max(z.accel_noise_density**2, TINY_VARIANCE))
    p.setGyroscopeCovariance(eye * max(z.gyro_noise_density**2, TINY_VARIANCE))
    p.setIntegrationCovariance(eye * TINY_VARIANCE)
    p.setBiasAccCovariance(eye * max(z.accel_random_walk**2, TINY_VARIANCE))
    p.setBiasOmegaCovariance(eye * max(z.gyro_random_walk**2, TINY_VARIANCE))
    return p


def imu_factor(
    params: gtsam.PreintegrationCombinedParams,
    U: F64,
    dts: F64,
    keys: tuple[int, int, int, int, int, int],
) -> gtsam.CombinedImuFactor:
    """The IMU samples U (k, 6) (specific force, angular rate; body FRD) held over dts (k,)
    between two keyframes; keys (pose i, velocity i, pose j, velocity j, bias i, bias j)."""
    pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
    for u, dt in zip(U, dts, strict=True):
        if dt > 0:
            pim.integrateMeasurement(u[0:3], u[3:6], float(dt))
    return gtsam.CombinedImuFactor(*keys, pim)


def odometry_factor(
    model: OdometryModel, U: F64, dts: F64, keys: tuple[int, int], planar_sigma: float
) -> gtsam.BetweenFactorPose3:
    """The relative pose (body i -> body j) the wheel odometry U (k, 2) over dts (k,)
    integrates to, from the model's own step (`propagate` from the origin, yaw 0, so its
    (x, y, yaw) are in body i's frame)."""
    x, _, Q = propagate(model, np.zeros(3), U, dts)
    dx, dy, dyaw = x
    c, s = np.cos(dyaw), np.sin(dyaw)
    # tangent [w; t] at the measured pose: translation error in body j's frame
    A = np.zeros((6, 3))
    A[2, 2] = 1.0
    A[3:5, 0:2] = np.array([[c, s], [-s, c]])
    cov = A @ Q @ A.T
    for k in (0, 1, 5):  # roll, pitch, height: fixed by the 3-DOF model
        cov[k, k] += planar_sigma**2
    cov += np.eye(6) * TINY_VARIANCE
    measured = gtsam.Pose3(gtsam.Rot3.Rz(dyaw), np.array([dx, dy, 0.0]))
    return gtsam.BetweenFactorPose3(*keys, measured, gtsam.noiseModel.Gaussian.Covariance(cov))


def _wna_covariance(q: float, dt: float) -> F64:
    """(6, 6) white-noise-acceleration covariance of (position, velocity)-like pairs."""
    a, b, c = dt**3 / 3.0, dt**2 / 2.0, dt
    eye = np.eye(3)
    cov = np.block([[eye * a, eye * b], [eye * b, eye * c]]) * q
    return cov + np.eye(6) * TINY_VARIANCE


def _translation_error(dt: float) -> Callable[..., F64]:
    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> F64:
        k = this.keys()
        Ti, Tj = values.atPose3(k[0]), values.atPose3(k[2])
        vi, vj = values.atVector(k[1]), values.atVector(k[3])
        e = np.concatenate([Tj.translation() - Ti.translation() - vi * dt, vj - vi])
        if H is not None:
            Hi = np.zeros((6, 6))
            Hi[0:3, 3:6] = -Ti.rotation().matrix()
            Hj = np.zeros((6, 6))
            Hj[0:3, 3:6] = Tj.rotation().matrix()
            _fill_jacobians(H, Hi, Hj, dt)
        return e

    return error


def _fill_jacobians(H: list, H_pose_i: F64, H_pose_j: F64, dt: float) -> None:
    """The Jacobians of a white-noise pair error [a_j - a_i - r_i dt; r_j - r_i] over keys
    (pose i, rate i, pose j, rate j), given the pose blocks."""
    H[0] = H_pose_i
    H[1] = np.vstack([-np.eye(3) * dt, -np.eye(3)])
    H[2] = H_pose_j
    H[3] = np.vstack([np.zeros((3, 3)), np.eye(3)])


def _rotation_error(dt: float) -> Callable[..., F64]:
    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> F64:
        k = this.keys()
        Ri, Rj = values.atPose3(k[0]).rotation(), values.atPose3(k[2]).rotation()
        wi, wj = values.atVector(k[1]), values.atVector(k[3])
        M = Ri.between(Rj)
        phi = gtsam.Rot3.Logmap(M)
        e = np.concatenate([phi - wi * dt, wj - wi])
        if H is not None:
            Jinv = gtsam.Rot3.LogmapDerivative(phi)
            Hi = np.zeros((6, 6))
            Hi[0:3, 0:3] = -Jinv @ M.matrix().T
            Hj = np.zeros((6, 6))
            Hj[0:3, 0:3] = Jinv
            _fill_jacobians(H, Hi, Hj, dt)
        return e

    return error


def constant_velocity_factors(
    model: ConstantVelocityModel, dt: float, keys: tuple[int, int, int, int, int, int]
) -> list[gtsam.CustomFactor]:
    """The two white-noise priors (module docstring) between keyframes dt s apart; keys
    (pose i, nav velocity i, body rate i, pose j, nav velocity j, body rate j)."""
    xi, vi, wi, xj, vj, wj = keys
    qa, qw = model.accel_noise_density**2, model.angular_accel_noise_density**2
    return [
        gtsam.CustomFactor(
            gtsam.noiseModel.Gaussian.Covariance(_wna_covariance(qa, dt)),
            [xi, vi, xj, vj],
            _translation_error(dt),
        ),
        gtsam.CustomFactor(
            gtsam.noiseModel.Gaussian.Covariance(_wna_covariance(qw, dt)),
            [xi, wi, xj, wj],
            _rotation_error(dt),
        ),
    ]
