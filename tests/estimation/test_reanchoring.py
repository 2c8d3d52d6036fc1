"""Handing an anchor's last landmarks to a newer anchor (estimation/reanchoring.py): the
same nav-frame Gaussian before and after (points, covariances, cross-covariances with the
vehicle and between landmarks), a smaller state, and only the anchors the rule names."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.new_landmarks import _anchored
from cvslam_cli.estimation.reanchoring import hand_over
from cvslam_cli.estimation.vehicle import VehiclePose
from tests.estimation.test_landmark_coordinates import OBS, _move, _points, _state, _Vehicle

SIZE = (640, 480)


def _central_points(k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`_points` within a third of the image's half-width of its centre: still in view of
    a camera a few metres and degrees on."""
    p, cov = _points(k, rng)
    p[:, :2] *= 0.3
    return p, cov


def _three_anchors(rng: np.random.Generator):
    """A state with anchors of 1, 4 and 2 landmarks, the vehicle moved after each, and a
    fourth anchor cloned at the end with 3 new landmarks (as `NewLandmarks.add` makes one)."""
    st = _state("inverse_depth", rng)
    vin = _Vehicle()
    keys = []
    for k in (1, 4, 2):
        _, key = _anchored(st, vin, VehiclePose.of(st, vin), *_central_points(k, rng), None)
        keys.append(key)
        _move(st)
    _, new_key = _anchored(st, vin, VehiclePose.of(st, vin), *_central_points(3, rng), None)
    return st, keys, new_key


def _nav_gaussian(st) -> tuple[np.ndarray, np.ndarray]:
    """Every landmark's nav point (L, 3) and the joint covariance of (vehicle, all nav
    points) ((9 + 3L) square), through the landmarks' Jacobians."""
    m, M = st.landmarks_nav()
    L = len(m)
    cols = st.landmark_columns(np.arange(L))
    G = np.zeros((9 + 3 * L, st.n))
    G[:9, :9] = np.eye(9)
    for j in range(L):
        G[9 + 3 * j : 12 + 3 * j, cols[j]] = M[j]
    return m, G @ st.P @ G.T


def test_hand_over_keeps_the_nav_gaussian_and_shrinks_the_state():
    rng = np.random.default_rng(21)
    st, keys, new_key = _three_anchors(rng)
    assert st.n_anchors == 4 and st.n == 9 + 4 * 6 + 3 * 10
    m0, C0 = _nav_gaussian(st)
    released = hand_over(
        st, new_key, OBS.R_cam_body[0], OBS.t_body_cam[0], OBS.K[0], SIZE, max_landmarks=2
    )
    assert released == 2 and st.n_anchors == 2 and st.n == 9 + 2 * 6 + 3 * 10
    assert st.anchor_rows(keys[0]) is None and st.anchor_rows(keys[2]) is None
    assert st.anchor_rows(keys[1]) is not None  # 4 landmarks: kept
    on = st.anchors_of(np.arange(10))
    np.testing.assert_array_equal(on, [new_key] + [keys[1]] * 4 + [new_key] * 5)
    m1, C1 = _nav_gaussian(st)
    np.testing.assert_allclose(m1, m0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(C1, C0, rtol=1e-9, atol=1e-9 * np.abs(C0).max())
    np.testing.assert_array_equal(st.P, st.P.T)
    assert np.linalg.eigvalsh(st.P).min() > -1e-9 * np.abs(st.P).max()


def test_no_hand_over_when_off_out_of_view_or_behind():
    rng = np.random.default_rng(22)
    st, keys, new_key = _three_anchors(rng)
    n = st.n
    assert (
        hand_over(
            st, new_key, OBS.R_cam_body[0], OBS.t_body_cam[0], OBS.K[0], SIZE, max_landmarks=0
        )
        == 0
    )
    assert st.n == n
    # a landmark outside the new anchor's image: its anchor keeps both of its landmarks
    far = st.landmark_index([5])[0]
    st.x[far[0]] += 5.0  # alpha: far to the side of the first anchor's view
    assert (
        hand_over(
            st, new_key, OBS.R_cam_body[0], OBS.t_body_cam[0], OBS.K[0], SIZE, max_landmarks=2
        )
        == 1
    )
    assert st.anchor_rows(keys[2]) is not None and st.anchor_rows(keys[0]) is None
    n = st.n
    # every point behind the new anchor's camera: each light anchor keeps its landmarks
    R_back = -OBS.R_cam_body[0]  # a camera looking the other way sees every point behind it
    assert hand_over(st, new_key, R_back, OBS.t_body_cam[0], OBS.K[0], SIZE, max_landmarks=2) == 0
    assert st.n == n and st.n_anchors == 3
