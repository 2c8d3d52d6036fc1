from __future__ import annotations

import numpy as np

from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, make_T
from cvslam_cli.geometry.stereo import (
    projection_matrices,
    triangulate,
    triangulation_covariance,
)

K = np.array([[450.0, 0, 376], [0, 452, 240], [0, 0, 1]])


def _rig(rectified: bool) -> StereoRig:
    R = np.eye(3) if rectified else euler_zyx_to_matrix(0.01, -0.015, 0.005)
    left = CameraModel(752, 480, K)
    right = CameraModel(752, 480, K * [[1.01], [1.0], [1]], T_body_cam=make_T(R, [0.5, 0, 0]))
    return StereoRig(left, right)


def _project(M, p):
    h = p @ M[:, :3].T + M[:, 3]
    return h[:, :2] / h[:, 2:3]


def test_triangulation_exact_on_both_rigs():
    rng = np.random.default_rng(0)
    p = np.column_stack(
        [rng.uniform(-20, 20, 300), rng.uniform(-15, 15, 300), rng.uniform(10, 80, 300)]
    )
    for rectified in (True, False):
        Ml, Mr = projection_matrices(_rig(rectified))
        np.testing.assert_allclose(
            triangulate(Ml, Mr, _project(Ml, p), _project(Mr, p)), p, rtol=1e-9
        )


def test_rectified_disparity_and_covariance_match_the_textbook():
    rig = StereoRig(
        CameraModel(752, 480, K),
        CameraModel(752, 480, K, T_body_cam=make_T(np.eye(3), [0.5, 0, 0])),
    )
    Ml, Mr = projection_matrices(rig)
    p = np.array([[1.0, -2.0, 40.0]])
    ul, ur = _project(Ml, p), _project(Mr, p)
    assert np.isclose(ul[0, 0] - ur[0, 0], 450.0 * 0.5 / 40.0, rtol=1e-12)  # d = f b / z
    assert np.isclose(ul[0, 1], ur[0, 1], atol=1e-12)
    cov = triangulation_covariance(Ml, Mr, ul, ur, sigma_px=0.5)[0]
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    # depth std ~ z^2 sigma_d / (f b), sigma_d = sqrt(2) sigma for independent pixels
    expected = 40.0**2 * np.sqrt(2) * 0.5 / (452.0 * 0.5)
    assert abs(np.sqrt(cov[2, 2]) / expected - 1) < 0.05


def test_covariance_matches_monte_carlo():
    rng = np.random.default_rng(1)
    Ml, Mr = projection_matrices(_rig(False))
    p = np.array([[3.0, 1.0, 30.0]])
    ul, ur = _project(Ml, p), _project(Mr, p)
    cov = triangulation_covariance(Ml, Mr, ul, ur, sigma_px=0.3)[0]
    n = 20000
    samples = triangulate(Ml, Mr, ul + rng.normal(0, 0.3, (n, 2)), ur + rng.normal(0, 0.3, (n, 2)))
    np.testing.assert_allclose(np.cov(samples.T), cov, rtol=0.1, atol=1e-6)
