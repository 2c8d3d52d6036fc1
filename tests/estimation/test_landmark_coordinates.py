"""Landmark coordinates: conversions round-trip, Jacobians equal finite differences, an
anchored landmark is the same nav-frame Gaussian as the Cartesian one made from the same
measurement, and its predicted pixels do not change when the whole scene is moved or turned
about the vertical (the directions no measurement observes)."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.association import predict_in_state
from cvslam_cli.estimation.landmark_coordinates import AnchoredInverseDepth, coordinates
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import InsModel
from cvslam_cli.estimation.new_landmarks import _anchored, _cartesian
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehiclePose
from cvslam_cli.geometry.rotations import euler_zyx_matrices, euler_zyx_to_matrix

K = np.array([[450.0, 0.0, 320.0], [0.0, 450.0, 240.0], [0.0, 0.0, 1.0]])
# a downward camera (optical z = body z), right camera 1.5 m along the body y axis
R_CB = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
OBS = StereoObservationModel(
    K=np.stack([K, K]),
    R_cam_body=np.stack([R_CB, R_CB]),
    t_body_cam=np.array([[0.2, 0.0, 0.1], [0.2, 1.5, 0.1]]),
)
INS = InsModel(InsNoise(2e-3, 1.7e-4), biases=False)


class _Vehicle:
    """The part of a VehicleInput the state helpers read."""

    name = "uav"
    obs = OBS
    model = INS
    right_cx_px = 0.0


def _spd(n: int, rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T / n + np.eye(n))


def _points(k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """k points 30-150 m in front of the left camera and their (k, 3, 3) covariances (a
    stereo-like 10 % depth uncertainty)."""
    z = rng.uniform(30, 150, k)
    p = np.column_stack([rng.uniform(-0.6, 0.6, (k, 2)) * z[:, None], z])
    cov = np.zeros((k, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = (z / 450.0) ** 2
    cov[:, 2, 2] = (0.1 * z) ** 2
    return p, cov


def _state(name: str, rng: np.random.Generator) -> JointState:
    x0 = np.concatenate([rng.normal(scale=50, size=3), rng.normal(size=3), [0.05, -0.03, 1.0]])
    return JointState([("uav", INS, x0, _spd(9, rng, 0.01))], coordinates(name))


def test_batched_rotations_equal_the_single_ones() -> None:
    e = np.random.default_rng(0).uniform(-1.5, 1.5, (5, 3))
    C, dC = euler_zyx_matrices(e)
    from cvslam_cli.geometry.rotations import euler_zyx_derivatives

    for i in range(5):
        np.testing.assert_allclose(C[i], euler_zyx_to_matrix(*e[i]), atol=1e-15)
        np.testing.assert_allclose(dC[i], euler_zyx_derivatives(*e[i]), atol=1e-15)


def test_inverse_depth_round_trip_and_jacobians() -> None:
    rng = np.random.default_rng(1)
    p_cam, _ = _points(30, rng)
    theta, G = AnchoredInverseDepth.from_camera(p_cam)
    np.testing.assert_allclose(
        theta[0], [p_cam[0, 0] / p_cam[0, 2], p_cam[0, 1] / p_cam[0, 2], 1 / p_cam[0, 2]]
    )
    back, D = AnchoredInverseDepth.camera_point(theta)
    np.testing.assert_allclose(back, p_cam, rtol=1e-12)
    np.testing.assert_allclose(D @ G, np.broadcast_to(np.eye(3), D.shape), atol=1e-9)
    for j in range(3):
        h = np.zeros(3)
        h[j] = 1e-4
        num = (
            AnchoredInverseDepth.from_camera(p_cam + h)[0]
            - AnchoredInverseDepth.from_camera(p_cam - h)[0]
        ) / 2e-4
        np.testing.assert_allclose(G[:, :, j], num, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("name", ["cartesian", "inverse_depth"])
def test_to_nav_jacobian_equals_finite_differences(name: str) -> None:
    rng = np.random.default_rng(2)
    coords = coordinates(name)
    k = 10
    if coords.anchored:
        theta, _ = AnchoredInverseDepth.from_camera(_points(k, rng)[0])
        params = np.column_stack(
            [rng.normal(scale=30, size=(k, 3)), rng.uniform(-1, 1, (k, 3)), theta]
        )
    else:
        params = rng.normal(scale=30, size=(k, 3))
    R = np.broadcast_to(R_CB, (k, 3, 3))
    t = np.broadcast_to(OBS.t_body_cam[0], (k, 3))
    _, M = coords.to_nav(params, R, t)
    for j in range(coords.size):
        h = np.zeros(coords.size)
        h[j] = 1e-6 * max(1.0, float(np.abs(params[:, j]).max()))
        num = (coords.to_nav(params + h, R, t)[0] - coords.to_nav(params - h, R, t)[0]) / (2 * h[j])
        np.testing.assert_allclose(M[:, :, j], num, rtol=1e-5, atol=1e-5)


def _move(st: JointState) -> None:
    """The vehicle a few metres and degrees on (its covariance kept)."""
    st.x[0:3] += [5.0, -1.0, 0.3]
    st.x[6:9] += [0.01, -0.02, 0.05]


def test_an_anchored_landmark_is_the_cartesian_gaussian() -> None:
    """The same measurements from the same poses, from a fresh anchor clone and from one
    made earlier at another pose: the same nav positions, covariances and cross-covariances
    with the vehicle, to rounding (both are the one linearised augmentation, written in
    other coordinates)."""
    rng = np.random.default_rng(3)
    batches = [_points(4, rng), _points(4, rng)]
    states = {}
    for name in ("cartesian", "inverse_depth"):
        st = _state(name, np.random.default_rng(4))
        key = None
        for p_cam, cov in batches:
            pose = VehiclePose.of(st, _Vehicle())
            if st.coords.anchored:
                _, key = _anchored(st, _Vehicle(), pose, p_cam, cov, key)
            else:
                _cartesian(st, _Vehicle(), pose, p_cam, cov)
            _move(st)
        states[name] = st
    cart, anch = states["cartesian"], states["inverse_depth"]
    assert anch.n_anchors == 1 and anch.n == cart.n + 6
    np.testing.assert_allclose(anch.landmarks(), cart.landmarks(), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(
        anch.landmark_covariances(), cart.landmark_covariances(), rtol=1e-9, atol=1e-9
    )
    v = cart.vehicles["uav"].index
    cols = anch.landmark_columns(np.arange(8))
    _, M = anch.landmarks_nav()
    cross_anch = M @ anch.P[cols[:, :, None], v[None, None, :]]
    cross_cart = cart.P[cart.landmark_index(np.arange(8))[:, :, None], v[None, None, :]]
    np.testing.assert_allclose(cross_anch, cross_cart, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", ["cartesian", "inverse_depth"])
def test_moving_or_turning_the_whole_scene_is_unobservable(name: str) -> None:
    """H N = 0 for N a translation of everything, and a turn of everything about the nav
    vertical (vehicle position and yaw, anchors' position and yaw, Cartesian landmarks'
    position), at linearisation points away from the ones the landmarks were made at."""
    rng = np.random.default_rng(5)
    st = _state(name, rng)
    vin = _Vehicle()
    key = None
    for new_anchor in (True, False, True):  # a clone, landmarks that share it, another clone
        key = None if new_anchor else key
        pose = VehiclePose.of(st, vin)
        if st.coords.anchored:
            _, key = _anchored(st, vin, pose, *_points(6, rng), key)
        else:
            _cartesian(st, vin, pose, *_points(6, rng))
        _move(st)
    assert st.n_anchors == (2 if st.coords.anchored else 0)
    st.x = st.x + rng.normal(scale=1e-2, size=st.n) * np.abs(st.x).clip(1e-2)  # "after updates"
    pose = VehiclePose.of(st, vin)
    slots = np.arange(st.n_landmarks)
    pred, _ = predict_in_state(st, pose, slots, np.eye(4))
    cols = st.landmark_columns(slots)
    e_z = np.array([0.0, 0.0, 1.0])
    for direction in ("x", "y", "z", "yaw"):
        N = np.zeros(st.n)
        if direction == "yaw":
            N[0:3] = np.cross(e_z, st.x[0:3])
            N[8] = 1.0
        else:
            N["xyz".index(direction)] = 1.0
        for a in range(st.n_anchors):
            rows = st._anchor_rows[a]
            N[rows[:3]] = np.cross(e_z, st.x[rows[:3]]) if direction == "yaw" else N[0:3]
            N[rows[5]] = 1.0 if direction == "yaw" else 0.0
        if not st.coords.anchored:
            own = st.landmark_index(slots)
            m = st.x[own]
            N[own] = np.cross(e_z, m) if direction == "yaw" else N[0:3]
        HN = pred.H_v @ N[pose.index] + np.einsum("kij,kj->ki", pred.H_m, N[cols])
        scale = np.abs(pred.H_v).max() * np.abs(N).max()
        assert np.abs(HN).max() < 1e-7 * scale, direction


def test_removing_landmarks_drops_unused_anchors_and_keeps_the_rest() -> None:
    rng = np.random.default_rng(6)
    st = _state("inverse_depth", rng)
    vin = _Vehicle()
    for _ in range(3):
        _anchored(st, vin, VehiclePose.of(st, vin), *_points(4, rng), None)
        _move(st)
    m, cov = st.landmarks(), st.landmark_covariances()
    P_before = st.P.copy()
    gone = np.array([0, 1, 2, 3, 9])  # every landmark of the first anchor, one of the third
    kept = st.remove_landmarks(gone)
    assert st.n_anchors == 2 and st.n == 9 + 2 * 6 + 3 * 7
    np.testing.assert_array_equal(kept, [4, 5, 6, 7, 8, 10, 11])
    np.testing.assert_allclose(st.landmarks(), m[kept], atol=1e-12)
    np.testing.assert_allclose(st.landmark_covariances(), cov[kept], atol=1e-12)
    np.testing.assert_array_equal(st.P[:9, :9], P_before[:9, :9])
    # positive semi-definite (clones made with no motion in between equal the vehicle's pose)
    assert np.linalg.eigvalsh(st.P).min() > -1e-12
