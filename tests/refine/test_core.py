"""The pure parts of refine: keyframe selection, pose covariance conversions, the motion
factors (Jacobians against finite differences, exact at the true motion), the observation
file and its landmark ids under `--single`."""

from __future__ import annotations

from types import SimpleNamespace

import gtsam
import numpy as np
import pytest

from cvslam_cli.estimation.motion.models import ConstantVelocityModel, OdometryModel
from cvslam_cli.estimation.slam import _merged_observations
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, make_T
from cvslam_cli.io.observations_file import load_observations, save_observations
from cvslam_cli.records.observations import ObservationTable
from cvslam_cli.refine.graph import V, W, X
from cvslam_cli.refine.keyframes import keep_observations, select_keyframes
from cvslam_cli.refine.motion_factors import constant_velocity_factors, odometry_factor
from cvslam_cli.refine.pose_covariance import pose_cov_from_tangent, tangent_cov_from_pose


def test_keyframes_every_nth_and_the_last():
    assert select_keyframes(7, 3).tolist() == [0, 3, 6]
    assert select_keyframes(8, 3).tolist() == [0, 3, 6, 7]
    assert select_keyframes(5, 1).tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError):
        select_keyframes(5, 0)


def test_observations_kept_at_keyframes_of_landmarks_seen_twice():
    vehicle = np.array([0, 0, 0, 1, 1, 0])
    stamp = np.array([10, 20, 30, 20, 30, 20])
    lid = np.array([5, 5, 7, 7, 9, 5])  # the last repeats (vehicle 0, stamp 20, landmark 5)
    kept = keep_observations(vehicle, stamp, lid, [np.array([10, 20]), np.array([20, 30])])
    # landmark 7: at stamp 30 of vehicle 0 (not a keyframe) and 20 of vehicle 1 -> once: out
    # landmark 9: once -> out; landmark 5: keyframes 0 and 1 of vehicle 0, the repeat dropped
    assert kept.landmark_ids.tolist() == [5]
    assert kept.rows.tolist() == [0, 1]
    assert kept.keyframe.tolist() == [0, 1]


def test_pose_covariance_round_trip_and_position_axes():
    rng = np.random.default_rng(0)
    T = make_T(euler_zyx_to_matrix(0.1, -0.2, 2.5), np.array([1.0, 2.0, -3.0]))
    A = rng.normal(size=(6, 6))
    cov = A @ A.T
    back = pose_cov_from_tangent(T, tangent_cov_from_pose(T, cov))
    np.testing.assert_allclose(back, cov, atol=1e-10)
    # a body-frame translation variance along body x is the nav variance along R[:, 0]
    tangent = np.zeros((6, 6))
    tangent[3, 3] = 4.0
    pc = pose_cov_from_tangent(T, tangent)
    np.testing.assert_allclose(pc[:3, :3], 4.0 * np.outer(T[:3, 0], T[:3, 0]), atol=1e-12)


def _numeric_jacobians(factor, values, keys, eps=1e-6):
    out = []
    base = factor.unwhitenedError(values)
    for k in keys:
        dim = 6 if k == keys[0] or k == keys[2] else 3
        J = np.zeros((len(base), dim))
        for i in range(dim):
            d = np.zeros(dim)
            d[i] = eps
            vals = gtsam.Values(values)
            if dim == 6:
                vals.update(k, values.atPose3(k).retract(d))
            else:
                vals.update(k, values.atVector(k) + d)
            J[:, i] = (factor.unwhitenedError(vals) - base) / eps
        out.append(J)
    return out


def test_constant_velocity_factor_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    values = gtsam.Values()
    for i in (0, 1):
        R = euler_zyx_to_matrix(*rng.normal(scale=0.3, size=3))
        values.insert(X(i), gtsam.Pose3(make_T(R, rng.normal(size=3))))
        values.insert(V(i), rng.normal(size=3))
        values.insert(W(i), rng.normal(size=3))
    model = ConstantVelocityModel(2.0, 0.5)
    factors = constant_velocity_factors(model, 0.1, (X(0), V(0), W(0), X(1), V(1), W(1)))
    for f in factors:
        keys = list(f.keys())
        lin = f.linearize(values)
        A, _ = lin.jacobian()
        # the whitened Jacobian blocks of the keys, unwhitened by the noise model's R
        R = f.noiseModel().R()
        analytic = np.linalg.solve(R, A)
        numeric = np.hstack(_numeric_jacobians(f, values, keys))
        np.testing.assert_allclose(analytic, numeric, atol=1e-4)


def test_constant_velocity_factor_is_zero_on_constant_motion():
    values = gtsam.Values()
    v = np.array([10.0, 2.0, -1.0])
    w = np.array([0.0, 0.0, 0.3])
    dt = 0.1
    R0 = euler_zyx_to_matrix(0.0, 0.0, 0.2)
    values.insert(X(0), gtsam.Pose3(make_T(R0, np.zeros(3))))
    R1 = R0 @ gtsam.Rot3.Expmap(w * dt).matrix()
    values.insert(X(1), gtsam.Pose3(make_T(R1, v * dt)))
    for i in (0, 1):
        values.insert(V(i), v)
        values.insert(W(i), w)
    model = ConstantVelocityModel(2.0, 0.5)
    for f in constant_velocity_factors(model, dt, (X(0), V(0), W(0), X(1), V(1), W(1))):
        np.testing.assert_allclose(f.unwhitenedError(values), 0.0, atol=1e-12)


def test_odometry_factor_measures_the_arc_the_robot_drove():
    model = OdometryModel(0.05, 0.01, z_nav_m=-0.3)
    U = np.array([[1.0, 0.5]] * 10)  # 1 m/s, turning at 0.5 rad/s, for 1 s
    dts = np.full(10, 0.1)
    yaw0 = 0.7
    T0 = make_T(euler_zyx_to_matrix(0.0, 0.0, yaw0), np.array([3.0, 4.0, -0.3]))
    # the exact arc: radius v / w, turned by w t
    r, a = 1.0 / 0.5, 0.5
    d_body = np.array([r * np.sin(a), r * (1 - np.cos(a)), 0.0])
    T1 = make_T(euler_zyx_to_matrix(0.0, 0.0, yaw0 + a), T0[:3, 3] + T0[:3, :3] @ d_body)
    f = odometry_factor(model, U, dts, (X(0), X(1)), 1e-3)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T0))
    values.insert(X(1), gtsam.Pose3(T1))
    np.testing.assert_allclose(f.unwhitenedError(values), 0.0, atol=1e-9)


def test_single_mode_renumbers_the_observed_landmark_ids_like_the_map(tmp_path):
    rng = np.random.default_rng(2)
    a = ObservationTable.concatenate(["uav1"], [(0, [1, 2], [0, 2], rng.normal(size=(2, 4)))])
    b = ObservationTable.concatenate(["uav2"], [(0, [3], [1], rng.normal(size=(1, 4)))])
    # merge_results numbers run k's landmarks after the runs before it (merge_archives)
    runs = [SimpleNamespace(observations=a), SimpleNamespace(observations=b)]
    merged = _merged_observations(runs, np.cumsum([0, 3, 2]))
    assert merged is not None
    assert merged.vehicles == ("uav1", "uav2")
    assert merged.vehicle.tolist() == [0, 0, 1]
    assert merged.landmark_id.tolist() == [0, 2, 4]  # uav2's ids after uav1's 3 landmarks
    path = tmp_path / "observations.npz"
    save_observations(path, merged)
    back = load_observations(path)
    assert back.vehicles == merged.vehicles
    np.testing.assert_array_equal(back.z_px, merged.z_px)
    np.testing.assert_array_equal(back.landmark_id, merged.landmark_id)
    first = path.read_bytes()
    save_observations(path, back)
    assert path.read_bytes() == first
