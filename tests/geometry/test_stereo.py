from __future__ import annotations

import numpy as np

from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, make_T
from cvslam_cli.geometry.stereo import (
    _reprojection,
    _triangulate_dlt,
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


def _uav_rig() -> StereoRig:
    """`uav2_paper`'s rectified pair: fx = fy 450, a 1.5 m baseline."""
    K_uav = np.array([[450.0, 0, 375.5], [0, 450.0, 239.5], [0, 0, 1]])
    return StereoRig(
        CameraModel(752, 480, K_uav),
        CameraModel(752, 480, K_uav, T_body_cam=make_T(np.eye(3), [1.5, 0, 0])),
    )


def test_noisy_pixels_give_the_least_squares_point_in_pixels():
    """On a rig that is not rectified: no step lowers the reprojection error (its gradient
    vanishes) and the point reprojects at least as well as the linear (DLT) one."""
    rng = np.random.default_rng(2)
    Ml, Mr = projection_matrices(_rig(False))
    p = np.column_stack(
        [rng.uniform(-20, 20, 200), rng.uniform(-15, 15, 200), rng.uniform(10, 80, 200)]
    )
    ul = _project(Ml, p) + rng.normal(0, 0.7, (200, 2))
    ur = _project(Mr, p) + rng.normal(0, 0.7, (200, 2))
    X = triangulate(Ml, Mr, ul, ur)
    uv = np.concatenate([ul, ur], axis=1)
    theta = np.column_stack([X[:, 0] / X[:, 2], X[:, 1] / X[:, 2], 1.0 / X[:, 2]])
    r, J = _reprojection(Ml, Mr, theta, uv)
    # the gradient J^T r against its scale |J| |r| (each column of J in its own units)
    gradient = np.abs(np.einsum("nki,nk->ni", J, r))
    scale = np.linalg.norm(J, axis=1) * np.linalg.norm(r, axis=1)[:, None]
    assert np.all(gradient <= 1e-9 * scale)
    D = _triangulate_dlt(Ml, Mr, ul, ur)
    err = np.sum((np.concatenate([_project(Ml, X), _project(Mr, X)], axis=1) - uv) ** 2, 1)
    err_dlt = np.sum((np.concatenate([_project(Ml, D), _project(Mr, D)], axis=1) - uv) ** 2, 1)
    assert np.all(err <= err_dlt + 1e-12) and np.mean(err < err_dlt - 1e-6) > 0.5


def test_a_rectified_pair_gives_inverse_depth_linear_in_the_disparity():
    """Rectified: alpha = (u_l - cx) / fx, beta from the mean row, rho = d / (fx b), so the
    inverse depth is unbiased under pixel noise; the linear (DLT) point, which trades row
    disagreement for depth, is 1.1 % too near at 100 m with 0.5 px (module docstring)."""
    rig = _uav_rig()
    Ml, Mr = projection_matrices(rig)
    rng = np.random.default_rng(3)
    n = 50_000
    p = np.array([[10.0, -20.0, 100.0]])
    ul = _project(Ml, p) + rng.normal(0, 0.5, (n, 2))
    ur = _project(Mr, p) + rng.normal(0, 0.5, (n, 2))
    X = triangulate(Ml, Mr, ul, ur)
    np.testing.assert_allclose(X[:, 0] / X[:, 2], (ul[:, 0] - 375.5) / 450.0, atol=1e-12)
    np.testing.assert_allclose(
        X[:, 1] / X[:, 2], (0.5 * (ul[:, 1] + ur[:, 1]) - 239.5) / 450.0, atol=1e-12
    )
    rho = 1.0 / X[:, 2]
    np.testing.assert_allclose(rho, (ul[:, 0] - ur[:, 0]) / (450.0 * 1.5), rtol=1e-10)
    # the mean's standard error: 10.5 % / sqrt(n) = 0.05 %
    assert abs(rho.mean() * 100.0 - 1.0) < 0.0025
    rho_dlt = 1.0 / _triangulate_dlt(Ml, Mr, ul, ur)[:, 2]
    assert rho_dlt.mean() * 100.0 - 1.0 > 0.008
