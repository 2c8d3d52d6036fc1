from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from cvslam_cli.geometry.rotations import (
    euler_zyx_to_matrix,
    invert_T,
    make_T,
    matrix_to_euler_zyx,
    matrix_to_quat_xyzw,
    nearest_rotation,
    quat_xyzw_to_matrix,
    so3_log,
)


def test_quaternion_matrix_round_trip():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    R = quat_xyzw_to_matrix(q)
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(matrix_to_quat_xyzw(R), q, atol=1e-12)


def test_quaternion_convention_is_hamilton_xyzw():
    # 90 degrees about z maps x to y
    q = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    np.testing.assert_allclose(quat_xyzw_to_matrix(q) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_euler_zyx_round_trip_and_yaw_meaning():
    rng = np.random.default_rng(1)
    for _ in range(100):
        rpy = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi])
        C = euler_zyx_to_matrix(*rpy)
        np.testing.assert_allclose(matrix_to_euler_zyx(C), rpy, atol=1e-12)
    # yaw 90 degrees: body x (forward) points east (nav y)
    np.testing.assert_allclose(
        euler_zyx_to_matrix(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15
    )


def test_transform_inverse():
    T = make_T(euler_zyx_to_matrix(0.1, -0.2, 0.3), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(T @ invert_T(T), np.eye(4), atol=1e-15)


def test_euler_derivatives_equal_finite_differences():
    from cvslam_cli.geometry.rotations import euler_zyx_derivatives

    rpy = np.array([0.3, -0.4, 2.0])
    D = euler_zyx_derivatives(*rpy)
    h = 1e-7
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (euler_zyx_to_matrix(*(rpy + d)) - euler_zyx_to_matrix(*(rpy - d))) / (2 * h)
        np.testing.assert_allclose(D[k], fd, atol=1e-8)


def test_interpolate_poses_slerps_and_marks_stamps_outside():
    from cvslam_cli.geometry.rotations import interpolate_poses, quat_xyzw_to_matrix

    stamps = np.array([0, 1_000_000_000, 3_000_000_000], dtype=np.int64)
    p = np.array([[0.0, 0, 0], [1.0, 2, 3], [3.0, 2, 3]])
    yaw = np.array([0.0, 0.4, 1.2])
    q = np.c_[np.zeros((3, 2)), np.sin(yaw / 2), np.cos(yaw / 2)]
    at = np.array([-1, 0, 500_000_000, 2_000_000_000, 3_000_000_000, 3_000_000_001], np.int64)
    got_p, got_R, ok = interpolate_poses(stamps, p, q, at)
    assert ok.tolist() == [False, True, True, True, True, False]
    assert np.isnan(got_p[0]).all() and np.isnan(got_R[-1]).all()
    np.testing.assert_allclose(got_p[2], [0.5, 1.0, 1.5])
    np.testing.assert_allclose(got_p[3], [2.0, 2.0, 3.0])
    for k, want_yaw in ((1, 0.0), (2, 0.2), (3, 0.8), (4, 1.2)):
        want = quat_xyzw_to_matrix(np.array([0, 0, np.sin(want_yaw / 2), np.cos(want_yaw / 2)]))
        np.testing.assert_allclose(got_R[k], want, atol=1e-12)


def test_so3_log_is_axis_times_angle():
    rng = np.random.default_rng(4)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(1e-6, 3.0)
        R = Rotation.from_rotvec(axis * angle).as_matrix()
        np.testing.assert_allclose(so3_log(R), axis * angle, atol=1e-9)
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))


def test_nearest_rotation_of_a_perturbed_rotation():
    R = Rotation.from_euler("zyx", [0.3, -0.2, 0.1]).as_matrix()
    noisy = R + 1e-4 * np.random.default_rng(0).standard_normal((3, 3))
    back = nearest_rotation(noisy)
    np.testing.assert_allclose(back @ back.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(back) > 0
    np.testing.assert_allclose(back, R, atol=1e-3)
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-12)
