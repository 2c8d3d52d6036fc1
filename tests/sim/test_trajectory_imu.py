"""Simulator motion truth, IMU and odometry models, and the reference strapdown integrator."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.geometry.gravity import G_NAV_M_S2
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, matrix_to_euler_zyx
from cvslam_cli.sim.imu import ImuNoise, simulate_imu, true_imu
from cvslam_cli.sim.odometry import OdometryNoise, simulate_odometry
from cvslam_cli.sim.strapdown import integrate_strapdown, local_cubic_coefficients
from cvslam_cli.sim.trajectory import (
    StationaryTrajectory,
    Trajectory,
    euler_zyx_to_matrix_batch,
    waypoint_trajectory,
)

# A ~60 s loop at 10 m/s with turns (bank up to ~14 deg), climbs and descents (|v_z| ~3 m/s).
UAV_WAYPOINTS_NAV_M = np.array(
    [
        [0.0, 0.0, -40.0],
        [80.0, 10.0, -50.0],
        [120.0, 70.0, -65.0],
        [60.0, 120.0, -55.0],
        [0.0, 80.0, -35.0],
        [-60.0, 120.0, -45.0],
        [-110.0, 60.0, -60.0],
        [-60.0, 0.0, -50.0],
    ]
)
UGV_WAYPOINTS_NAV_M = np.array(
    [[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [40.0, 20.0, 0.0], [20.0, 35.0, 0.0], [0.0, 20.0, 0.0]]
)
IMU_RATE_HZ = 200.0


@pytest.fixture(scope="module")
def uav() -> Trajectory:
    return waypoint_trajectory(UAV_WAYPOINTS_NAV_M, 10.0, kind="uav", closed=True)


@pytest.fixture(scope="module")
def ugv() -> Trajectory:
    return waypoint_trajectory(UGV_WAYPOINTS_NAV_M, 2.0, kind="ugv", closed=True)


def _vee(W: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 3) axial vector of the skew-symmetric part."""
    A = 0.5 * (W - np.swapaxes(W, 1, 2))
    return np.stack([A[:, 2, 1], A[:, 0, 2], A[:, 1, 0]], axis=1)


def _rotation_error_rad(C_a: np.ndarray, C_b: np.ndarray) -> np.ndarray:
    """(N,) angle of C_a^T C_b, accurate for tiny angles (no arccos)."""
    return np.arcsin(
        np.clip(np.linalg.norm(_vee(np.einsum("nji,njk->nik", C_a, C_b)), axis=1), 0, 1)
    )


def _imu_times(duration_s: float) -> np.ndarray:
    return np.arange(round(duration_s * IMU_RATE_HZ) + 1) / IMU_RATE_HZ


# --- trajectory ------------------------------------------------------------------------------


def test_attitude_matches_rotations_module(uav: Trajectory) -> None:
    s = uav.sample(np.linspace(0.0, 50.0, 7))
    for e, C in zip(s.euler_rad, s.C_nav_body, strict=True):
        np.testing.assert_allclose(C, euler_zyx_to_matrix(*e), atol=1e-15)
        np.testing.assert_allclose(matrix_to_euler_zyx(C), e, atol=1e-12)
    np.testing.assert_allclose(euler_zyx_to_matrix_batch(s.euler_rad), s.C_nav_body)
    # yaw follows the horizontal velocity
    body_v = s.v_body_m_s
    assert np.all(body_v[:, 0] > 0)
    np.testing.assert_allclose(
        s.euler_rad[:, 2], np.arctan2(s.v_nav_m_s[:, 1], s.v_nav_m_s[:, 0]), atol=1e-15
    )


def test_rates_match_finite_differences(uav: Trajectory, ugv: Trajectory) -> None:
    t = np.linspace(0.3, 59.0, 97)
    for traj in (uav, ugv):
        s = traj.sample(t)
        h = 1e-4
        sp, sm = traj.sample(t + h), traj.sample(t - h)
        # ω^b: skew(ω) = C^T Ċ
        W = np.einsum("nji,njk->nik", s.C_nav_body, (sp.C_nav_body - sm.C_nav_body) / (2 * h))
        np.testing.assert_allclose(_vee(W), s.omega_body_rad_s, rtol=0, atol=1e-6)
        alpha_fd = (sp.omega_body_rad_s - sm.omega_body_rad_s) / (2 * h)
        np.testing.assert_allclose(alpha_fd, s.alpha_body_rad_s2, rtol=0, atol=1e-6)
        h = 1e-3
        sp, sm = traj.sample(t + h), traj.sample(t - h)
        v_fd = (sp.p_nav_m - sm.p_nav_m) / (2 * h)
        a_fd = (sp.v_nav_m_s - sm.v_nav_m_s) / (2 * h)
        np.testing.assert_allclose(v_fd, s.v_nav_m_s, rtol=0, atol=1e-6)
        np.testing.assert_allclose(a_fd, s.a_nav_m_s2, rtol=0, atol=1e-6)


def test_uav_motion_is_realistic(uav: Trajectory) -> None:
    s = uav.sample(_imu_times(uav.duration_s))
    speed = np.linalg.norm(s.v_nav_m_s, axis=1)
    assert speed.min() > 5.0 and speed.max() < 15.0
    assert np.abs(s.euler_rad[:, 0]).max() > np.radians(8)  # it turns (banks)
    assert np.abs(s.v_nav_m_s[:, 2]).max() > 1.0  # it climbs and descends
    assert np.abs(s.euler_rad[:, :2]).max() < uav.max_tilt_rad
    assert uav.distance_m() == pytest.approx(np.sum(speed[:-1]) / IMU_RATE_HZ, rel=1e-3)


def test_closed_loop_returns_to_start(uav: Trajectory) -> None:
    t0, t1 = uav.t0_s, uav.t1_s
    a, b = uav.sample(np.array([t0, t0 + 1e-7])), uav.sample(np.array([t1, t1 - 1e-7]))
    np.testing.assert_allclose(b.p_nav_m[0], a.p_nav_m[0], atol=1e-9)
    np.testing.assert_allclose(b.p_nav_m[0], UAV_WAYPOINTS_NAV_M[0], atol=1e-9)
    np.testing.assert_allclose(b.v_nav_m_s[0], a.v_nav_m_s[0], atol=1e-9)
    np.testing.assert_allclose(b.a_nav_m_s2[0], a.a_nav_m_s2[0], atol=1e-9)
    np.testing.assert_allclose(b.C_nav_body[0], a.C_nav_body[0], atol=1e-9)
    np.testing.assert_allclose(b.omega_body_rad_s[0], a.omega_body_rad_s[0], atol=1e-9)
    # continuous across the closing point (just before vs just after)
    np.testing.assert_allclose(b.C_nav_body[1], a.C_nav_body[1], atol=1e-6)
    # later laps repeat the first one
    lap2 = uav.sample(np.array([t1 + 3.0]))
    np.testing.assert_allclose(lap2.p_nav_m, uav.sample(np.array([t0 + 3.0])).p_nav_m, atol=1e-9)


def test_open_trajectory_and_validation() -> None:
    traj = waypoint_trajectory(UAV_WAYPOINTS_NAV_M[:4], 8.0, kind="uav", t0_s=5.0)
    s = traj.sample(np.array([traj.t0_s, traj.t1_s]))
    np.testing.assert_allclose(s.p_nav_m, UAV_WAYPOINTS_NAV_M[[0, 3]], atol=1e-9)
    assert traj.t0_s == 5.0
    np.testing.assert_allclose(np.linalg.norm(s.v_nav_m_s, axis=1), 8.0)
    with pytest.raises(ValueError, match="outside"):
        traj.sample(np.array([traj.t1_s + 1.0]))
    wp = UAV_WAYPOINTS_NAV_M
    with pytest.raises(ValueError, match="at least 2"):
        waypoint_trajectory(wp[:1], 5.0, kind="uav")
    with pytest.raises(ValueError, match="at least 3"):
        waypoint_trajectory(wp[:2], 5.0, kind="uav", closed=True)
    with pytest.raises(ValueError, match="speed"):
        waypoint_trajectory(wp, 0.0, kind="uav")
    with pytest.raises(ValueError, match="coincide"):
        waypoint_trajectory(wp[[0, 1, 1, 2]], 5.0, kind="uav")
    with pytest.raises(ValueError, match="level"):
        waypoint_trajectory(wp, 5.0, kind="ugv")
    with pytest.raises(ValueError, match="heading"):
        waypoint_trajectory(np.array([[0, 0, 0], [0, 0, -50.0]]), 5.0, kind="uav")
    with pytest.raises(ValueError, match="kind"):
        waypoint_trajectory(wp, 5.0, kind="boat")  # type: ignore[arg-type]
    # a loop given with its start repeated at the end is the same loop
    again = waypoint_trajectory(np.vstack([wp, wp[:1]]), 10.0, kind="uav", closed=True)
    assert again.t1_s == pytest.approx(waypoint_trajectory(wp, 10.0, kind="uav", closed=True).t1_s)


def test_ugv_is_level(ugv: Trajectory) -> None:
    s = ugv.sample(np.linspace(0.0, ugv.duration_s, 500))
    assert np.all(s.euler_rad[:, :2] == 0.0)
    assert np.all(s.p_nav_m[:, 2] == 0.0)
    assert np.all(s.v_nav_m_s[:, 2] == 0.0)
    np.testing.assert_allclose(s.v_body_m_s[:, 1:], 0.0, atol=1e-12)  # non-holonomic
    np.testing.assert_allclose(s.omega_body_rad_s[:, :2], 0.0, atol=1e-15)


# --- IMU -------------------------------------------------------------------------------------


def test_true_imu_at_rest_reads_minus_gravity() -> None:
    rest = StationaryTrajectory(np.array([1.0, 2.0, -3.0]), np.zeros(3), 0.0, 1.0)
    gyro, accel = true_imu(rest.sample(np.array([0.0, 0.5])), G_NAV_M_S2)
    np.testing.assert_array_equal(gyro, 0.0)
    np.testing.assert_allclose(accel, [[0.0, 0.0, -9.80665]] * 2, atol=1e-15)
    # pitched up 90 deg: gravity along body x
    up = StationaryTrajectory(np.zeros(3), np.array([0.0, np.pi / 2, 0.0]), 0.0, 1.0)
    _, accel = true_imu(up.sample(np.array([0.0])), G_NAV_M_S2)
    np.testing.assert_allclose(accel[0], [9.80665, 0.0, 0.0], atol=1e-12)


def test_noise_free_imu_integrates_to_truth(uav: Trajectory) -> None:
    t = _imu_times(60.0)
    truth = uav.sample(t)
    imu = simulate_imu(uav, t, None, None)
    np.testing.assert_array_equal(imu.gyro_bias_rad_s, 0.0)
    p, v, C = integrate_strapdown(
        t,
        imu.gyro_rad_s,
        imu.accel_m_s2,
        truth.p_nav_m[0],
        truth.v_nav_m_s[0],
        truth.C_nav_body[0],
        G_NAV_M_S2,
    )
    p_err = np.linalg.norm(p - truth.p_nav_m, axis=1).max()
    v_err = np.linalg.norm(v - truth.v_nav_m_s, axis=1).max()
    att_err = _rotation_error_rad(C, truth.C_nav_body).max()
    print(
        f"\nstrapdown, noise-free {IMU_RATE_HZ:.0f} Hz IMU, 60 s, {uav.distance_m():.0f} m loop: "
        f"max |dp| = {p_err:.3e} m, max |dv| = {v_err:.3e} m/s, max attitude = {att_err:.3e} rad"
    )
    assert p_err < 5e-3
    assert att_err < 1e-6


def test_strapdown_short_series_and_constant_rotation() -> None:
    # Constant rate about body z at rest (f = -g rotated, which stays (0, 0, -g)): exact yaw.
    for n in (2, 3, 9):
        t = np.linspace(0.0, 1.0, n)
        gyro = np.tile([0.0, 0.0, 0.3], (n, 1))
        accel = np.tile([0.0, 0.0, -9.80665], (n, 1))
        p, v, C = integrate_strapdown(
            t, gyro, accel, np.zeros(3), np.zeros(3), np.eye(3), G_NAV_M_S2
        )
        np.testing.assert_allclose(p, 0.0, atol=1e-12)
        np.testing.assert_allclose(v, 0.0, atol=1e-12)
        expected = euler_zyx_to_matrix_batch(np.column_stack([0 * t, 0 * t, 0.3 * t]))
        assert _rotation_error_rad(C, expected).max() < 2e-6 * (t[1] - t[0]) ** 4  # RK4
    with pytest.raises(ValueError, match="strictly increasing"):
        integrate_strapdown(
            np.array([0.0, 0.0]),
            np.zeros((2, 3)),
            np.zeros((2, 3)),
            np.zeros(3),
            np.zeros(3),
            np.eye(3),
            G_NAV_M_S2,
        )


def test_local_cubic_is_exact_for_cubics() -> None:
    t = np.sort(np.random.default_rng(3).uniform(0.0, 2.0, 12))
    y = 1.0 - 2.0 * t + 0.5 * t**2 + 0.25 * t**3
    coeffs = local_cubic_coefficients(t, y)
    u = np.linspace(0.0, 1.0, 5)
    tt = t[:-1, None] + u[None, :] * np.diff(t)[:, None]
    y_expected = 1.0 - 2.0 * tt + 0.5 * tt**2 + 0.25 * tt**3
    np.testing.assert_allclose(coeffs @ (u[None, :] ** np.arange(4)[:, None]), y_expected)


def test_noisy_imu_drift_is_superlinear(uav: Trajectory) -> None:
    t = _imu_times(60.0)
    truth = uav.sample(t)
    checkpoints = np.arange(2, 61, 2) * int(IMU_RATE_HZ)
    errors = []
    for seed in range(8):
        imu = simulate_imu(uav, t, ImuNoise(), np.random.default_rng(seed))
        p, _, _ = integrate_strapdown(
            t,
            imu.gyro_rad_s,
            imu.accel_m_s2,
            truth.p_nav_m[0],
            truth.v_nav_m_s[0],
            truth.C_nav_body[0],
            G_NAV_M_S2,
        )
        errors.append(np.linalg.norm(p[checkpoints] - truth.p_nav_m[checkpoints], axis=1))
    mean_err = np.mean(errors, axis=0)
    exponent = np.polyfit(np.log(t[checkpoints]), np.log(mean_err), 1)[0]
    print(
        f"\nnoisy IMU (ADIS16448 defaults), mean of 8 seeds: error at 10 s = {mean_err[4]:.2f} m, "
        f"at 60 s = {mean_err[-1]:.1f} m, log-log slope = {exponent:.2f}"
    )
    assert mean_err[-1] > 10.0
    assert 2.0 < exponent < 3.5


def test_imu_white_noise_statistics() -> None:
    n = 40_000
    t = np.arange(n) / IMU_RATE_HZ
    rest = StationaryTrajectory(np.zeros(3), np.array([0.1, -0.2, 1.0]), 0.0, t[-1])
    noise = ImuNoise(gyro_random_walk=0.0, accel_random_walk=0.0)
    imu = simulate_imu(rest, t, noise, np.random.default_rng(7))
    exact = simulate_imu(rest, t, None, None)
    np.testing.assert_array_equal(np.diff(imu.gyro_bias_rad_s, axis=0), 0.0)
    gyro_std = np.std(imu.gyro_rad_s - exact.gyro_rad_s, axis=0)
    accel_std = np.std(imu.accel_m_s2 - exact.accel_m_s2, axis=0)
    rate_sqrt = np.sqrt(IMU_RATE_HZ)
    np.testing.assert_allclose(gyro_std, noise.gyro_noise_density * rate_sqrt, rtol=0.05)
    np.testing.assert_allclose(accel_std, noise.accel_noise_density * rate_sqrt, rtol=0.05)
    # bias random walk: increments of std rw·√dt
    rw = simulate_imu(rest, t, ImuNoise(), np.random.default_rng(8))
    step_std = np.std(np.diff(rw.gyro_bias_rad_s, axis=0), axis=0)
    np.testing.assert_allclose(step_std, ImuNoise().gyro_random_walk / rate_sqrt, rtol=0.05)
    with pytest.raises(ValueError, match="must be a finite value >= 0"):
        ImuNoise(gyro_noise_density=-1.0)


def test_determinism(uav: Trajectory, ugv: Trajectory) -> None:
    t = _imu_times(5.0)
    a = simulate_imu(uav, t, ImuNoise(), np.random.default_rng(42))
    b = simulate_imu(uav, t, ImuNoise(), np.random.default_rng(42))
    c = simulate_imu(uav, t, ImuNoise(), np.random.default_rng(43))
    for name in ("gyro_rad_s", "accel_m_s2", "gyro_bias_rad_s", "accel_bias_m_s2"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.gyro_rad_s, c.gyro_rad_s)
    t = np.arange(0.0, 10.0, 0.02)
    o1 = simulate_odometry(ugv, t, OdometryNoise(), np.random.default_rng(5))
    o2 = simulate_odometry(ugv, t, OdometryNoise(), np.random.default_rng(5))
    for name in ("v_forward_m_s", "yaw_rate_rad_s", "x_m", "y_m", "yaw_rad"):
        np.testing.assert_array_equal(getattr(o1, name), getattr(o2, name))


# --- odometry --------------------------------------------------------------------------------


def test_odometry_exact_and_noisy(ugv: Trajectory) -> None:
    t = np.arange(0.0, ugv.duration_s, 1.0 / 50.0)
    truth = ugv.sample(t)
    exact = simulate_odometry(ugv, t, None, None)
    pos_err = np.hypot(exact.x_m - truth.p_nav_m[:, 0], exact.y_m - truth.p_nav_m[:, 1]).max()
    yaw_err = np.abs(np.angle(np.exp(1j * (exact.yaw_rad - truth.euler_rad[:, 2])))).max()
    assert pos_err < 1e-6
    assert yaw_err < 1e-8
    np.testing.assert_allclose(exact.v_forward_m_s, np.linalg.norm(truth.v_nav_m_s, axis=1))
    noisy = simulate_odometry(ugv, t, OdometryNoise(), np.random.default_rng(1))
    final_err = np.hypot(noisy.x_m[-1] - truth.p_nav_m[-1, 0], noisy.y_m[-1] - truth.p_nav_m[-1, 1])
    distance = ugv.distance_m()
    print(
        f"\nodometry over {distance:.0f} m: exact max error {pos_err:.2e} m, "
        f"noisy final error {final_err:.2f} m ({100 * final_err / distance:.1f} %)"
    )
    assert final_err > 0.01 * distance
