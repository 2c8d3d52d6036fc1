"""Stereo observation model (eq. 19): agrees with the camera projection, analytic Jacobians
equal finite differences, and the inverse model undoes it with a consistent covariance."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, invert_T, make_T
from cvslam_cli.geometry.stereo import projection_matrices, triangulation_covariance
from cvslam_cli.sim.scenario import StereoRigSpec
from cvslam_cli.sim.vehicles import build_rig

RNG = np.random.default_rng(11)


@pytest.fixture(params=[True, False], ids=["rectified", "unrectified"])
def rig(request):
    return build_rig(
        "t", StereoRigSpec(rectified=request.param, tilt_deg=5.0, lever_arm_m=(0.3, -0.1, 0.2))
    )


def _scene(n=40):
    p = np.array([10.0, -5.0, -80.0])
    euler = np.array([0.05, -0.08, 1.1])
    C = euler_zyx_to_matrix(*euler)
    # landmarks below the vehicle, inside the downward camera's view
    body = np.column_stack(
        [RNG.uniform(-20, 20, n), RNG.uniform(-30, 30, n), RNG.uniform(60, 90, n)]
    )
    return p, euler, body @ C.T + p


def test_prediction_equals_projection_through_the_camera_matrices(rig):
    model = StereoObservationModel.from_rig(rig)
    p, euler, m = _scene()
    z, _, _ = model.predict(p, euler, m)
    T_nav_left = make_T(euler_zyx_to_matrix(*euler), p) @ rig.left.T_body_cam
    M_l, M_r = projection_matrices(rig)
    p_left = np.column_stack([m, np.ones(len(m))]) @ invert_T(T_nav_left)[:3].T
    for M, cols in ((M_l, slice(0, 2)), (M_r, slice(2, 4))):
        h = p_left @ M[:, :3].T + M[:, 3]
        np.testing.assert_allclose(z[:, cols], h[:, :2] / h[:, 2:3], atol=1e-9)


def test_projection_is_the_predictions_pixels_bit_for_bit(rig):
    """`project` (the visibility tests' pixels) is `predict` without its Jacobians: the same
    numbers, so that choosing it changes no decision."""
    model = StereoObservationModel.from_rig(rig)
    p, euler, m = _scene()
    z, _, _ = model.predict(p, euler, m)
    assert np.array_equal(model.project(p, euler, m), z)
    assert np.array_equal(model.project(p, euler, m[3]), z[3:4])  # one point, as (1, 4)


def test_analytic_jacobians_equal_finite_differences(rig):
    model = StereoObservationModel.from_rig(rig)
    p, euler, m = _scene(10)
    _, H_pose, H_m = model.predict(p, euler, m)
    x0 = np.concatenate([p, euler])
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        zp, _, _ = model.predict((x0 + d)[:3], (x0 + d)[3:], m)
        zm, _, _ = model.predict((x0 - d)[:3], (x0 - d)[3:], m)
        np.testing.assert_allclose(H_pose[:, :, k], (zp - zm) / (2 * h), rtol=1e-5, atol=1e-4)
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        zp, _, _ = model.predict(p, euler, m + d)
        zm, _, _ = model.predict(p, euler, m - d)
        np.testing.assert_allclose(H_m[:, :, k], (zp - zm) / (2 * h), rtol=1e-6, atol=1e-6)


def test_inverse_model_round_trip_and_covariance(rig):
    model = StereoObservationModel.from_rig(rig)
    p, euler, m = _scene(200)
    T_nav_left = make_T(euler_zyx_to_matrix(*euler), p) @ rig.left.T_body_cam
    p_cam = np.column_stack([m, np.ones(len(m))]) @ invert_T(T_nav_left)[:3].T
    cov_cam = np.tile(np.diag([0.01, 0.02, 1.0]), (len(m), 1, 1))
    back, cov = model.landmark_from_camera_point(p, euler, p_cam, cov_cam)
    np.testing.assert_allclose(back, m, atol=1e-9)
    np.testing.assert_allclose(np.linalg.eigvalsh(cov), np.linalg.eigvalsh(cov_cam), rtol=1e-9)
    # pose uncertainty: Monte Carlo over the pose agrees with the propagated covariance
    cov_pose = np.diag([0.5, 0.5, 1.0, 0.01, 0.01, 0.02]) ** 2
    _, cov_full = model.landmark_from_camera_point(
        p, euler, p_cam[:1], np.zeros((1, 3, 3)), cov_pose
    )
    draws = RNG.multivariate_normal(np.concatenate([p, euler]), cov_pose, size=20000)
    samples = np.array(
        [
            model.landmark_from_camera_point(d[:3], d[3:], p_cam[:1], np.zeros((1, 3, 3)))[0][0]
            for d in draws
        ]
    )
    # (20000 draws: sampling error of an element ~0.01 against diagonals ~1)
    np.testing.assert_allclose(np.cov(samples.T), cov_full[0], rtol=0.06, atol=0.03)
    # and the triangulation covariance from extract passes through (shape check)
    M_l, M_r = projection_matrices(rig)
    assert triangulation_covariance(M_l, M_r, np.zeros((1, 2)), np.zeros((1, 2)), 0.3).shape == (
        1,
        3,
        3,
    )
