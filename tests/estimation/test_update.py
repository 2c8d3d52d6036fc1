"""The visual update (`update.py`): a rectified rig's three rows per observation give the
update of the four rows (state, covariance and NIS), for the EKF and NH-infinity."""

from __future__ import annotations

import copy
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from cvslam_cli.estimation.association import LandmarkPrediction
from cvslam_cli.estimation.filters import FilterSettings
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import InsModel
from cvslam_cli.estimation.observation import BEARING_ROWS, StereoObservationModel
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.update import ExtraRows, VisualUpdater
from cvslam_cli.estimation.vehicle import VehiclePose
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.sim.scenario import StereoRigSpec
from cvslam_cli.sim.vehicles import build_rig

SIGMA_PX = 0.6
INS = InsModel(InsNoise(2e-3, 1.7e-4), biases=False)


def _rectified_prediction(
    rng: np.random.Generator, k: int
) -> tuple[JointState, LandmarkPrediction, np.ndarray]:
    """A UAV's state (p, v, Psi) with k Cartesian landmarks below it, their prediction
    through a rectified rig's model, and noisy observations z (k, 4)."""
    obs = StereoObservationModel.from_rig(
        build_rig("t", StereoRigSpec(rectified=True, tilt_deg=5.0, lever_arm_m=(0.3, -0.1, 0.2)))
    )
    assert obs.rectified
    p, euler = np.array([10.0, -5.0, -80.0]), np.array([0.05, -0.08, 1.1])
    body = np.column_stack(
        [rng.uniform(-20, 20, k), rng.uniform(-30, 30, k), rng.uniform(60, 90, k)]
    )
    m = body @ euler_zyx_to_matrix(*euler).T + p
    x0 = np.concatenate([p, np.zeros(3), euler])
    st = JointState([("uav", INS, x0, np.eye(9) * 1e-4)])
    slots = st.add_landmarks(m, np.eye(3 * k) * 0.04, np.zeros((3 * k, st.n)))
    A = rng.normal(size=(st.n, st.n))
    st.P[...] = A @ A.T / st.n * 1e-3 + np.eye(st.n) * 1e-4
    z_pred, H_pose, H_m = obs.predict(p, euler, m)
    J = np.zeros((6, 9))
    J[:3, :3] = np.eye(3)
    J[3:, 6:] = np.eye(3)
    pred = LandmarkPrediction(
        slots, z_pred, H_pose @ J, H_m, np.zeros((k, 4, 4)), rectified=obs.rectified
    )
    return st, pred, z_pred + rng.normal(0, SIGMA_PX, (k, 4))


@pytest.mark.parametrize("kind", ["ekf", "hinf"])
def test_three_rows_of_a_rectified_rig_give_the_four_rows_update(kind: str) -> None:
    """(u_l, (v_l + v_r) / 2, u_r) with noise sigma^2 diag(1, 1/2, 1) carries what the four
    rows say about the state: x, P and the NIS (with the v_l - v_r term) are the same."""
    rng = np.random.default_rng(5)
    st, pred, z = _rectified_prediction(rng, 12)
    np.testing.assert_allclose(pred.z[:, 1], pred.z[:, 3], rtol=1e-12)
    np.testing.assert_allclose(pred.H_v[:, 1], pred.H_v[:, 3], rtol=1e-9, atol=1e-9)
    settings = FilterSettings(kind, gamma=0.5, c_v=1.3)  # a gamma that bounds (hinf)
    rows = np.arange(len(pred.slots))
    three, four = copy.deepcopy(st), copy.deepcopy(st)
    res3 = VisualUpdater(three, settings, SIGMA_PX).update(np.arange(9), pred, rows, z, ["uav"])
    four_pred = replace(pred, rectified=False)
    res4 = VisualUpdater(four, settings, SIGMA_PX).update(np.arange(9), four_pred, rows, z, ["uav"])
    assert not np.allclose(three.x, st.x)
    np.testing.assert_allclose(three.x, four.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(three.P, four.P, rtol=0, atol=1e-14)
    assert res3.nis == pytest.approx(res4.nis, rel=1e-10)
    assert res3.gamma == res4.gamma
    if kind == "hinf":
        ekf = copy.deepcopy(st)
        VisualUpdater(ekf, FilterSettings("ekf", c_v=1.3), SIGMA_PX).update(
            np.arange(9), pred, rows, z, ["uav"]
        )
        assert np.trace(three.P[:9, :9]) > np.trace(ekf.P[:9, :9]) * 1.001  # the bound acts


def test_a_rig_not_rectified_keeps_its_four_rows() -> None:
    """An unrectified rig (v_l != v_r) is recognised and its prediction says so."""
    spec = StereoRigSpec(rectified=False, tilt_deg=5.0, lever_arm_m=(0.3, -0.1, 0.2))
    assert not StereoObservationModel.from_rig(build_rig("t", spec)).rectified


def _far_off(rng: np.random.Generator, k: int = 20):
    """A UAV 80 m above k landmarks known to centimetres, its estimate `offset_m` off the
    pose the observations z (k, 4) were taken from, its covariance (10 m, 0.1 rad) saying
    so: a return to mapped ground after seconds of dead reckoning."""
    obs = StereoObservationModel.from_rig(build_rig("t", StereoRigSpec(rectified=True)))
    vin = SimpleNamespace(name="uav", obs=obs, model=INS, right_cx_px=0.0)
    p_true, euler_true = np.array([10.0, -5.0, -80.0]), np.array([0.02, -0.03, 1.1])
    body = np.column_stack(
        [rng.uniform(-20, 20, k), rng.uniform(-30, 30, k), rng.uniform(70, 90, k)]
    )
    m = body @ euler_zyx_to_matrix(*euler_true).T + p_true
    offset_m = np.array([7.0, -6.0, 2.0])
    x0 = np.concatenate([p_true + offset_m, np.zeros(3), euler_true + np.array([0.0, 0.0, 0.08])])
    P0 = np.diag([100.0] * 3 + [1.0] * 3 + [1e-4, 1e-4, 0.01])
    st = JointState([("uav", INS, x0, P0)])
    slots = st.add_landmarks(m, np.eye(3 * k) * 1e-4, np.zeros((3 * k, st.n)))
    z, _, _ = obs.predict(p_true, euler_true, m)
    z = z + rng.normal(0, SIGMA_PX, (k, 4))
    return st, vin, slots, z, p_true


@pytest.mark.parametrize("kind", ["ekf", "hinf"])
def test_the_iterated_update_makes_a_correction_one_linearisation_cannot(kind: str) -> None:
    """Metres off at 80 m range: one linearised update leaves most of a metre of error under
    a covariance of decimetres; relinearised at its own estimate (the iterated EKF) it lands
    at the truth to within its covariance. With one linearisation it is `update`, bit for
    bit."""
    results = {}
    for iterations in (1, 5):
        st, vin, slots, z, p_true = _far_off(np.random.default_rng(3))
        up = VisualUpdater(st, FilterSettings(kind=kind, gamma=30.0), SIGMA_PX)
        pred, _ = up.predict(VehiclePose.of(st, vin), slots)
        rows = np.arange(len(slots))
        res, done = up.iterated_update(vin, pred, rows, z, ["uav"], iterations=iterations)
        assert done == iterations if iterations == 1 else 2 < done <= iterations
        e = st.x[:3] - p_true
        nees = float(e @ np.linalg.solve(st.P[:3, :3], e))
        results[iterations] = (np.linalg.norm(e), nees, st.x.copy(), st.P.copy(), res.nis)
    st, vin, slots, z, _ = _far_off(np.random.default_rng(3))
    up = VisualUpdater(st, FilterSettings(kind=kind, gamma=30.0), SIGMA_PX)
    pred, _ = up.predict(VehiclePose.of(st, vin), slots)
    once = up.update(st.vehicles["uav"].index, pred, np.arange(len(slots)), z, ["uav"])
    np.testing.assert_array_equal(results[1][2], st.x)
    np.testing.assert_array_equal(results[1][3], st.P)
    assert results[1][4] == once.nis
    (err1, nees1, *_), (err5, nees5, *_) = results[1], results[5]
    # one linearisation: 0.75 m off, and sure of itself (beyond chi2(3) at 0.999); iterated:
    # 0.27 m, inside its covariance
    assert nees1 > 16.27 > 7.81 > nees5 and err5 < 0.5 * err1


def test_the_iterated_update_stops_where_the_update_cost_is_stationary() -> None:
    """At convergence x is the minimum of the update's cost (the iterated EKF is
    Gauss-Newton on it): P0^-1 (x - x0) = H(x)^T R^-1 (z - h(x)) + H_e^T R_e^-1 (r - H_e (x
    - x0)), with the stereo rows relinearised at x and linear rows of the sliding window's
    kind (`ExtraRows`) stacked in; checked on the gradient, in units of its terms."""
    st, vin, slots, z, _ = _far_off(np.random.default_rng(4), k=8)
    rng = np.random.default_rng(7)
    cols_e = np.array([3, 4, 5, 9, 10])  # the velocity and a landmark's columns
    H_e = rng.normal(size=(4, len(cols_e)))
    R_e = np.diag(rng.uniform(0.5, 2.0, 4))
    extra = ExtraRows(rng.normal(size=4), H_e, cols_e, R_e)
    up = VisualUpdater(st, FilterSettings(kind="ekf"), SIGMA_PX)
    x0, P0 = st.x.copy(), st.P.copy()
    pred, _ = up.predict(VehiclePose.of(st, vin), slots)
    _, done = up.iterated_update(
        vin, pred, np.arange(len(slots)), z, ["uav"], extra=extra, iterations=20
    )
    pred, _ = up.predict(VehiclePose.of(st, vin), slots)  # relinearised at x
    H = np.zeros((4 * len(slots), st.n))
    v_idx = st.vehicles["uav"].index
    lm_cols = st.landmark_columns(slots)
    for j in range(len(slots)):
        H[4 * j : 4 * j + 4, v_idx] = pred.H_v[j]
        H[4 * j : 4 * j + 4, lm_cols[j]] += pred.H_m[j]
    dx = st.x - x0
    prior = np.linalg.solve(P0, dx)
    stereo = H.T @ (z - pred.z).reshape(-1) / SIGMA_PX**2
    window = np.zeros(st.n)
    window[cols_e] = H_e.T @ np.linalg.solve(R_e, extra.r - H_e @ dx[cols_e])
    scale = np.abs(prior).max()
    assert 2 < done <= 20 and scale > 1.0  # a real correction, in a few linearisations
    np.testing.assert_allclose(prior, stereo + window, rtol=0, atol=1e-6 * scale)


@pytest.mark.parametrize("kind", ["ekf", "hinf"])
def test_another_vehicles_landmark_observed_with_its_own_pixel_noise(kind: str) -> None:
    """`fuse.association.other_vehicle_pixel_sigma_px`: landmarks flagged by
    `association.noise_scale` are predicted (S), tested and updated with the pixel noise
    scaled by their factor: with every landmark flagged by 4, the update is the one of a
    filter whose pixel noise is twice as large (x, P and NIS, the v difference's included);
    with the factor on some landmarks only, S grows for them alone."""
    st, vin, slots, z, _ = _far_off(np.random.default_rng(7), k=8)
    settings = FilterSettings(kind=kind, gamma=30.0)
    rows = np.arange(len(slots))
    scaled, doubled = copy.deepcopy(st), copy.deepcopy(st)
    up = VisualUpdater(scaled, settings, SIGMA_PX)
    pred, _ = up.predict(VehiclePose.of(scaled, vin), slots, np.full(len(slots), 4.0))
    up2 = VisualUpdater(doubled, settings, 2 * SIGMA_PX)
    pred2, _ = up2.predict(VehiclePose.of(doubled, vin), slots)
    np.testing.assert_allclose(pred.S, pred2.S, rtol=1e-12)
    res = up.update(scaled.vehicles["uav"].index, pred, rows, z, ["uav"])
    res2 = up2.update(doubled.vehicles["uav"].index, pred2, rows, z, ["uav"])
    np.testing.assert_allclose(scaled.x, doubled.x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(scaled.P, doubled.P, rtol=0, atol=1e-12)
    assert res.nis == pytest.approx(res2.nis, rel=1e-9)
    assert not np.allclose(scaled.x, st.x)
    some = np.where(rows % 2 == 0, 4.0, 1.0)
    pred_some, _ = VisualUpdater(copy.deepcopy(st), settings, SIGMA_PX).predict(
        VehiclePose.of(st, vin), slots, some
    )
    pred_none, _ = VisualUpdater(copy.deepcopy(st), settings, SIGMA_PX).predict(
        VehiclePose.of(st, vin), slots
    )
    R = np.eye(4) * SIGMA_PX**2 * settings.c_v**2
    np.testing.assert_allclose(pred_some.S - pred_none.S, (some - 1)[:, None, None] * R)


@pytest.mark.parametrize("rectified", [True, False], ids=["three_rows", "four_rows"])
def test_bearing_noise_scaled_per_observation(rectified: bool) -> None:
    """`bearing_scale` (octave_noise.py): observation j's noise is sigma^2 (I + (b_j - 1)
    BEARING_ROWS), its bearing's variance b_j times the filter's and its disparity's
    unchanged: the EKF update (x, P, NIS) equals the textbook one with that R over the four
    rows, with three rows per observation too; b = 1 is the update without it."""
    rng = np.random.default_rng(17)
    st, pred, z = _rectified_prediction(rng, 10)
    pred = replace(pred, rectified=rectified)
    k, rows, v_idx = len(pred.slots), np.arange(len(pred.slots)), np.arange(9)
    b = rng.uniform(0.3, 3.0, k)
    settings = FilterSettings("ekf")
    scaled, plain, unit = copy.deepcopy(st), copy.deepcopy(st), copy.deepcopy(st)
    res = VisualUpdater(scaled, settings, SIGMA_PX).update(
        v_idx, pred, rows, z, ["uav"], bearing_scale=b
    )
    # the textbook update
    H = np.zeros((4 * k, st.n))
    cols = st.landmark_columns(pred.slots)
    for j in range(k):
        H[4 * j : 4 * j + 4, v_idx] = pred.H_v[j]
        H[4 * j : 4 * j + 4, cols[j]] = pred.H_m[j]
    R = np.zeros((4 * k, 4 * k))
    for j in range(k):
        R[4 * j : 4 * j + 4, 4 * j : 4 * j + 4] = SIGMA_PX**2 * (
            np.eye(4) + (b[j] - 1) * BEARING_ROWS
        )
    S = H @ st.P @ H.T + R
    K = st.P @ H.T @ np.linalg.inv(S)
    r = (z - pred.z).ravel()
    np.testing.assert_allclose(scaled.x, st.x + K @ r, rtol=0, atol=1e-10)
    np.testing.assert_allclose(scaled.P, st.P - K @ S @ K.T, rtol=0, atol=1e-12)
    assert res.nis == pytest.approx(float(r @ np.linalg.solve(S, r)), rel=1e-8)
    # the bearing's variance is b_j times, the disparity's the same
    bearing = np.array([[0.5, 0, 0.5, 0], [0, 0.5, 0, 0.5]])
    disparity = np.array([[1.0, 0, -1.0, 0], [0, 1.0, 0, -1.0]])
    for j in range(3):
        R_j = R[4 * j : 4 * j + 4, 4 * j : 4 * j + 4]
        np.testing.assert_allclose(np.diag(bearing @ R_j @ bearing.T), b[j] * SIGMA_PX**2 / 2)
        np.testing.assert_allclose(np.diag(disparity @ R_j @ disparity.T), 2 * SIGMA_PX**2)
    VisualUpdater(plain, settings, SIGMA_PX).update(v_idx, pred, rows, z, ["uav"])
    VisualUpdater(unit, settings, SIGMA_PX).update(
        v_idx, pred, rows, z, ["uav"], bearing_scale=np.ones(k)
    )
    np.testing.assert_allclose(unit.x, plain.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(unit.P, plain.P, rtol=0, atol=1e-15)
    assert not np.allclose(scaled.x, plain.x, rtol=0, atol=1e-6)
