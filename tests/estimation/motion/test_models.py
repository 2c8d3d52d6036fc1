"""Motion models behind one interface: analytic Jacobians equal finite differences, process
noise is the input noise mapped into the state, `propagate` equals stepping one at a time,
and noise-free simulated motion input integrates to the simulator's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import (
    ConstantVelocityModel,
    InitialUncertainty,
    InsModel,
    MotionModel,
    OdometryModel,
    odometry_input,
    propagate,
)
from cvslam_cli.geometry.rotations import (
    euler_zyx_to_matrix,
    matrix_to_euler_zyx,
    quat_xyzw_to_matrix,
)
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.records.log import OdometryRecord, PoseRecord
from cvslam_cli.sim.imu import true_imu
from cvslam_cli.sim.odometry import simulate_odometry
from cvslam_cli.sim.scenario import SCENARIO_DIR, load_scenario
from cvslam_cli.sim.stage import run
from cvslam_cli.sim.trajectory import waypoint_trajectory

INS_NOISE = InsNoise(2e-3, 1.7e-4, 3e-3, 1.9e-5)
MODELS = {
    "ins15": InsModel(INS_NOISE),
    "ins9": InsModel(INS_NOISE, biases=False),
    "odometry": OdometryModel(0.01, 0.002, z_nav_m=-0.3),
    "constant_velocity": ConstantVelocityModel(0.5, 0.1),
}
INIT = InitialUncertainty(
    position_m=0.1,
    attitude_rad=0.01,
    velocity_m_s=0.2,
    angular_rate_rad_s=0.05,
    accel_bias_m_s2=0.02,
    gyro_bias_rad_s=1e-3,
)


def dead_reckoning(
    model: MotionModel, x0: np.ndarray, U: np.ndarray, dts: np.ndarray
) -> np.ndarray:
    """All states of K steps without any correction: X (K+1, n), X[0] = x0, X[k+1] the state
    after U[k] held over dts[k]."""
    X = np.empty((len(dts) + 1, model.n))
    X[0] = x = np.asarray(x0, dtype=float)
    U = np.asarray(U, dtype=float).reshape(len(dts), model.input_size)
    for k in range(len(dts)):
        x = model.step(x, U[k], float(dts[k]))[0]
        X[k + 1] = x
    return X


def _state(model: MotionModel, rng: np.random.Generator) -> np.ndarray:
    """A generic state (not level, not at rest) of `model`."""
    if model.kind == "ins":
        x = np.concatenate([[5.0, -3.0, -80.0], [9.0, 0.5, -0.3], [0.1, -0.2, 1.3]])
        if model.n == 15:
            x = np.concatenate([x, rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3)])
        return x
    if model.kind == "odometry":
        return np.array([3.0, -2.0, 2.5])
    return np.concatenate(
        [[5.0, -3.0, -80.0], [9.0, 0.5, -0.3], [0.1, -0.2, 1.3], [0.03, -0.05, 0.2]]
    )


def _input(model: MotionModel, rng: np.random.Generator) -> np.ndarray:
    if model.kind == "ins":
        return np.array([0.3, -0.2, -9.7, 0.02, -0.05, 0.1]) + rng.normal(0, 0.01, 6)
    if model.kind == "odometry":
        return np.array([1.5, 0.4]) + rng.normal(0, 0.01, 2)
    return np.zeros(0)


def _numeric_jacobian(fun, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = []
    for k in range(len(x)):
        d = np.zeros(len(x))
        d[k] = h
        cols.append((fun(x + d) - fun(x - d)) / (2 * h))
    return np.stack(cols, axis=1)


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * np.asarray(a)))


@pytest.mark.parametrize("name", list(MODELS))
def test_interface(name):
    model = MODELS[name]
    assert isinstance(model, MotionModel)
    assert model.kind in ("ins", "odometry", "constant_velocity")
    assert len(model.state_names) == model.n == len(set(model.state_names))
    assert {"ins": 6, "odometry": 2, "constant_velocity": 0}[model.kind] == model.input_size
    rng = np.random.default_rng(0)
    x, u = _state(model, rng), _input(model, rng)
    x_new, F, Q = model.step(x, u, 0.01)
    assert x_new.shape == (model.n,) and F.shape == Q.shape == (model.n, model.n)
    p, euler = model.pose(x)
    assert p.shape == euler.shape == (3,)
    assert model.pose_jacobian(x).shape == (6, model.n)
    P0 = model.initial_covariance(INIT)
    assert P0.shape == (model.n, model.n) and np.all(np.diag(P0) > 0)


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("dt", [0.005, 0.1])
def test_step_jacobian_equals_finite_differences(name, dt):
    model = MODELS[name]
    rng = np.random.default_rng(0)
    x, u = _state(model, rng), _input(model, rng)
    _, F, _ = model.step(x, u, dt)
    F_num = _numeric_jacobian(lambda s: model.step(s, u, dt)[0], x)
    np.testing.assert_allclose(F, F_num, atol=1e-7)


def test_odometry_jacobians_when_driving_straight():
    """The chord's sinc(w dt / 2) switches to its series near w = 0: values and Jacobians
    stay continuous there."""
    model = MODELS["odometry"]
    x = np.array([1.0, 2.0, 0.7])
    for w in (0.0, 1e-7, 3e-3, -0.8):
        u = np.array([2.0, w])
        _, F, Q = model.step(x, u, 0.05)
        np.testing.assert_allclose(
            F, _numeric_jacobian(lambda s, u=u: model.step(s, u, 0.05)[0], x), atol=1e-8
        )
        J_u = _numeric_jacobian(lambda v: model.step(x, v, 0.05)[0], u)
        q = np.array([model.speed_noise_density, model.yaw_rate_noise_density]) ** 2 / 0.05
        np.testing.assert_allclose(Q, J_u @ np.diag(q) @ J_u.T, rtol=1e-6, atol=1e-15)


@pytest.mark.parametrize("name", list(MODELS))
def test_pose_jacobian_equals_finite_differences(name):
    model = MODELS[name]
    x = _state(model, np.random.default_rng(0))
    J_num = _numeric_jacobian(lambda s: np.concatenate(model.pose(s)), x)
    np.testing.assert_allclose(model.pose_jacobian(x), J_num, atol=1e-9)


@pytest.mark.parametrize("name", list(MODELS))
def test_process_noise_is_the_input_noise_in_state_space(name):
    """Q is symmetric PSD and equals J_u diag(density^2 / dt) J_u^T (+ bias walks
    density^2 dt) for the sensor models; for constant velocity, level, it is the standard
    white-noise-acceleration block."""
    model = MODELS[name]
    rng = np.random.default_rng(0)
    x, u, dt = _state(model, rng), _input(model, rng), 0.02
    _, _, Q = model.step(x, u, dt)
    np.testing.assert_allclose(Q, Q.T, atol=0)
    assert np.linalg.eigvalsh(Q).min() > -1e-15 * max(1.0, np.abs(Q).max())
    if model.kind == "ins":
        J_u = _numeric_jacobian(lambda v: model.step(x, v, dt)[0], u)
        z = INS_NOISE
        q = np.array([z.accel_noise_density**2] * 3 + [z.gyro_noise_density**2] * 3) / dt
        expected = J_u @ np.diag(q) @ J_u.T
        if model.n == 15:
            expected[9:12, 9:12] += np.eye(3) * z.accel_random_walk**2 * dt
            expected[12:15, 12:15] += np.eye(3) * z.gyro_random_walk**2 * dt
        np.testing.assert_allclose(Q, expected, rtol=1e-6, atol=1e-18)
    elif model.kind == "odometry":
        J_u = _numeric_jacobian(lambda v: model.step(x, v, dt)[0], u)
        q = np.array([model.speed_noise_density, model.yaw_rate_noise_density]) ** 2 / dt
        np.testing.assert_allclose(Q, J_u @ np.diag(q) @ J_u.T, rtol=1e-6, atol=1e-18)
    else:
        x_level = x.copy()
        x_level[6:8] = 0.0
        _, _, Q = model.step(x_level, u, dt)
        block = np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        qa, qw = model.accel_noise_density**2, model.angular_accel_noise_density**2
        np.testing.assert_allclose(Q[np.ix_([0, 3], [0, 3])], qa * block, rtol=1e-12)
        np.testing.assert_allclose(Q[np.ix_([8, 11], [8, 11])], qw * block, rtol=1e-12)
        np.testing.assert_allclose(Q[0:3, 6:12], 0.0, atol=0)


@pytest.mark.parametrize("name", list(MODELS))
def test_propagate_equals_stepping_one_at_a_time(name):
    model = MODELS[name]
    rng = np.random.default_rng(0)
    K = 25
    x0 = _state(model, rng)
    U = np.stack([_input(model, rng) for _ in range(K)]).reshape(K, model.input_size)
    dts = rng.uniform(0.002, 0.03, K)
    A = rng.normal(size=(model.n, model.n))
    P0 = A @ A.T * 1e-3
    x, P = x0.copy(), P0.copy()
    for k in range(K):
        x, F, Q = model.step(x, U[k], dts[k])
        P = F @ P @ F.T + Q
    xK, F_total, Q_total = propagate(model, x0, U, dts)
    np.testing.assert_allclose(xK, x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(F_total @ P0 @ F_total.T + Q_total, P, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(Q_total, Q_total.T, atol=0)
    X = dead_reckoning(model, x0, U, dts)
    assert X.shape == (K + 1, model.n)
    np.testing.assert_array_equal(X[0], x0)
    np.testing.assert_allclose(X[-1], xK, rtol=1e-12, atol=1e-12)


def test_propagate_without_steps_and_bad_input():
    model = MODELS["ins15"]
    x0 = _state(model, np.random.default_rng(0))
    x, F, Q = propagate(model, x0, np.zeros((0, 6)), np.zeros(0))
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(F, np.eye(15))
    np.testing.assert_array_equal(Q, np.zeros((15, 15)))
    with pytest.raises(ValueError, match=r"expected shape \(2, 6\)"):
        propagate(model, x0, np.zeros((2, 3)), np.full(2, 0.005))
    with pytest.raises(ValueError, match="expected 15 numbers"):
        propagate(model, x0[:9], np.zeros((1, 6)), np.full(1, 0.005))
    with pytest.raises(ValueError, match=">= 0"):
        propagate(model, x0, np.zeros((1, 6)), np.array([-0.005]))
    # no-input model: an empty U is enough
    cv = MODELS["constant_velocity"]
    x_cv = _state(cv, np.random.default_rng(0))
    assert propagate(cv, x_cv, np.zeros(0), np.full(3, 0.1))[0].shape == (12,)
    with pytest.raises(ValueError, match=">= 0"):
        OdometryModel(-0.01, 0.002)


@pytest.mark.parametrize("name", list(MODELS))
def test_initial_state_has_the_given_pose(name):
    model = MODELS[name]
    p, euler = np.array([3.0, -4.0, -0.3]), np.array([0.05, -0.1, 2.0])
    v_nav, w_body = np.array([1.0, 2.0, -0.5]), np.array([0.01, 0.02, 0.3])
    if model.kind == "odometry":
        euler[:2] = 0.0
    x = model.initial_state(p, euler, v_nav, w_body)
    p_out, e_out = model.pose(x)
    np.testing.assert_allclose(p_out, p, atol=1e-15)
    np.testing.assert_allclose(e_out, euler, atol=1e-15)
    if model.kind == "ins":
        np.testing.assert_allclose(euler_zyx_to_matrix(*euler) @ x[3:6], v_nav, atol=1e-14)
        assert np.all(x[9:] == 0)
    if model.kind == "constant_velocity":
        np.testing.assert_array_equal(x[3:6], v_nav)
        np.testing.assert_array_equal(x[9:12], w_body)


@pytest.mark.parametrize("name", list(MODELS))
def test_with_pose_moves_the_pose_and_keeps_the_motion(name):
    """Relinearising at a new pose keeps the motion: the same body velocity and rates (nav
    velocity turned with the attitude), the same biases."""
    model = MODELS[name]
    p, euler = np.array([3.0, -4.0, -0.3]), np.array([0.05, -0.1, 2.0])
    v_nav, w_body = np.array([1.0, 2.0, -0.5]), np.array([0.01, 0.02, 0.3])
    p2, euler2 = np.array([13.0, 6.0, -1.3]), np.array([0.02, 0.04, 2.6])
    if model.kind == "odometry":
        euler[:2] = euler2[:2] = 0.0
        p2[2] = p[2] = model.z_nav_m
    x = model.initial_state(p, euler, v_nav, w_body)
    if model.kind == "ins":
        x[9:] = np.arange(1, model.n - 8) * 1e-3  # biases (if any)
    y = model.with_pose(x, p2, euler2)
    p_out, e_out = model.pose(y)
    np.testing.assert_allclose(p_out, p2, atol=1e-14)
    np.testing.assert_allclose(e_out, euler2, atol=1e-14)
    if model.kind == "ins":
        np.testing.assert_array_equal(y[3:6], x[3:6])
        np.testing.assert_array_equal(y[9:], x[9:])
    if model.kind == "constant_velocity":
        C, C2 = euler_zyx_to_matrix(*euler), euler_zyx_to_matrix(*euler2)
        np.testing.assert_allclose(C2.T @ y[3:6], C.T @ x[3:6], atol=1e-14)
        np.testing.assert_array_equal(y[9:12], x[9:12])


def test_ins_integrates_noise_free_imu_to_the_truth():
    traj = waypoint_trajectory(
        np.array([[0, 0, -80], [100, 20, -85], [150, 120, -80], [40, 160, -75]], float),
        10.0,
        kind="uav",
    )
    t = np.arange(0.0, 10.0, 0.005)
    m = traj.sample(t)
    gyro, acc = true_imu(m)
    samples = np.hstack([acc, gyro])
    model = MODELS["ins15"]
    x0 = model.initial_state(m.p_nav_m[0], m.euler_rad[0], m.v_nav_m_s[0], m.omega_body_rad_s[0])
    # eq. 1 with each sample held over the interval that follows it (first-order Euler)
    X = dead_reckoning(model, x0, samples[:-1], np.diff(t))
    assert np.linalg.norm(X[:, :3] - m.p_nav_m, axis=1).max() < 0.1
    assert np.abs(_wrap(X[:, 6:9] - m.euler_rad)).max() < 1e-3
    # the mean of the samples at the ends of each interval: a few centimetres after 10 s
    x, _, _ = propagate(model, x0, 0.5 * (samples[:-1] + samples[1:]), np.diff(t))
    assert np.linalg.norm(x[:3] - m.p_nav_m[-1]) < 0.03
    np.testing.assert_allclose(euler_zyx_to_matrix(*x[6:9]) @ x[3:6], m.v_nav_m_s[-1], atol=0.01)
    assert np.abs(_wrap(x[6:9] - m.euler_rad[-1])).max() < 1e-4
    np.testing.assert_array_equal(x[9:], 0.0)  # biases only move with corrections


def test_constant_velocity_is_exact_on_a_straight_line():
    model = MODELS["constant_velocity"]
    rng = np.random.default_rng(0)
    dts = rng.uniform(0.01, 0.2, 50)
    p0, v = np.array([10.0, -5.0, -30.0]), np.array([3.0, -1.0, 0.5])
    euler0, yaw_rate = np.array([0.0, 0.0, 0.3]), 0.2  # level, turning at a constant rate
    x0 = model.initial_state(p0, euler0, v, np.array([0.0, 0.0, yaw_rate]))
    X = dead_reckoning(model, x0, np.zeros(0), dts)
    T = np.concatenate([[0.0], np.cumsum(dts)])
    np.testing.assert_allclose(X[:, 0:3], p0 + T[:, None] * v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(X[:, 3:6], np.broadcast_to(v, (51, 3)), atol=0)
    np.testing.assert_allclose(X[:, 8], 0.3 + yaw_rate * T, rtol=1e-12)
    np.testing.assert_allclose(X[:, 6:8], 0.0, atol=0)


def _odometry_trajectory():
    waypoints = np.array(
        [[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [40.0, 20.0, 0.0], [20.0, 35.0, 0.0], [0.0, 20.0, 0.0]]
    )
    return waypoint_trajectory(waypoints, 2.0, kind="ugv", closed=True)


def test_odometry_model_reproduces_the_simulated_truth():
    traj = _odometry_trajectory()
    t = np.arange(0.0, 40.0, 0.02)  # 50 Hz
    odo = simulate_odometry(traj, t, None, None)
    m = traj.sample(t)
    assert np.ptp(m.euler_rad[:, 2]) > 1.0  # it turns
    model = OdometryModel(0.01, 0.002)
    x0 = model.initial_state(m.p_nav_m[0], m.euler_rad[0], m.v_nav_m_s[0], np.zeros(3))
    U = np.stack([odo.v_forward_m_s, odo.yaw_rate_rad_s], axis=1)
    X = dead_reckoning(model, x0, 0.5 * (U[:-1] + U[1:]), np.diff(t))
    assert np.abs(X[:, 0:2] - m.p_nav_m[:, 0:2]).max() < 1e-3
    assert np.abs(_wrap(X[:, 2] - m.euler_rad[:, 2])).max() < 1e-4


def _twist_record(linear, angular) -> OdometryRecord:
    return OdometryRecord(
        "robot1",
        0,
        "robot1/odom",
        "robot1/base_link",
        np.zeros(3),
        np.array([0.0, 0.0, 0.0, 1.0]),
        np.asarray(linear, float),
        np.asarray(angular, float),
        np.zeros((6, 6)),
        np.zeros((6, 6)),
    )


def test_odometry_input_frames():
    rec = _twist_record([1.2, 0.0, 0.0], [0.0, 0.0, 0.3])
    np.testing.assert_array_equal(odometry_input(rec), [1.2, 0.3])  # cvslam logs: FRD
    np.testing.assert_array_equal(odometry_input(rec, "flu"), [1.2, -0.3])  # ROS REP 103
    with pytest.raises(ValueError, match="expected 3 \\+ 3 numbers"):
        odometry_input(_twist_record([1.0, 0.0], [0.0, 0.0, 0.1]))


def test_odometry_of_a_simulated_log_integrates_to_its_ground_truth(tmp_path):
    """Through the log: the simulator's nav_msgs/Odometry twist (noise off), read back and
    converted by `odometry_input`, reproduces the logged ground truth; reading it as FLU
    would turn the robot the wrong way."""
    overrides = ["mode=landmarks"] + [
        f"vehicles.{v}.odometry.{k}=0"
        for v in ("robot1", "robot2")
        for k in (
            "speed_scale_error",
            "yaw_rate_bias_rad_s",
            "speed_noise_density",
            "yaw_rate_noise_density",
        )
    ]
    # the yard mission in 20 s: robot1 drives round three corners of the yard
    sc = load_scenario(SCENARIO_DIR / "ugv2_yard.yaml", overrides, duration_s=20.0)
    out = run(sc, tmp_path / "yard").out_dir
    recs = list(LogSet([McapLogSource(out / "robot1.mcap")], load_config().logs).records())
    odo = [r for r in recs if isinstance(r, OdometryRecord)]
    gt = [r for r in recs if isinstance(r, PoseRecord)]
    t_odo = np.array([r.stamp_ns for r in odo])
    t_gt = np.array([r.stamp_ns for r in gt])
    at_gt = np.searchsorted(t_odo, t_gt)
    assert np.array_equal(t_odo[at_gt], t_gt)
    p_gt = np.array([r.p_m for r in gt])
    yaw_gt = np.array([matrix_to_euler_zyx(quat_xyzw_to_matrix(r.q_xyzw))[2] for r in gt])
    assert np.ptp(np.unwrap(yaw_gt)) > 3.0
    model = OdometryModel(0.01, 0.002, z_nav_m=float(p_gt[0, 2]))
    x0 = model.initial_state(p_gt[0], np.array([0.0, 0.0, yaw_gt[0]]), np.zeros(3), np.zeros(3))
    errors = {}
    for frame in ("frd", "flu"):
        U = np.array([odometry_input(r, frame) for r in odo])
        X = dead_reckoning(model, x0, 0.5 * (U[:-1] + U[1:]), np.diff(t_odo) * 1e-9)
        errors[frame] = np.abs(X[at_gt, 0:2] - p_gt[:, 0:2]).max()
        if frame == "frd":
            assert np.abs(_wrap(X[at_gt, 2] - yaw_gt)).max() < 1e-3
            p, euler = model.pose(X[-1])
            assert p[2] == p_gt[-1, 2] and euler[0] == euler[1] == 0.0
    assert errors["frd"] < 0.01, errors
    assert errors["flu"] > 10.0, errors
