"""The sliding-window (MSCKF) update: point fit, null-space residuals, gate, the pinned
clones in the joint state, and the track book's bookkeeping (`window_update.py`,
`tracks.py`)."""

from __future__ import annotations

import copy

import numpy as np
from scipy.stats import chi2

from cvslam_cli.estimation.association import LandmarkPrediction
from cvslam_cli.estimation.filters import FilterSettings, GammaPolicy
from cvslam_cli.estimation.landmark_coordinates import coordinates
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import InsModel
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.settings import WindowSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.tracks import TrackBook, TrackObservations
from cvslam_cli.estimation.update import ExtraRows, VisualUpdater
from cvslam_cli.estimation.window_update import SlidingWindow, fit_points, track_residuals

K = np.array([[450.0, 0.0, 320.0], [0.0, 450.0, 240.0], [0.0, 0.0, 1.0]])
R_CB = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # downward camera
OBS = StereoObservationModel(
    K=np.stack([K, K]),
    R_cam_body=np.stack([R_CB, R_CB]),
    t_body_cam=np.array([[0.2, 0.0, 0.1], [0.2, 1.5, 0.1]]),
)
INS = InsModel(InsNoise(2e-3, 1.7e-4), biases=False)
SIGMA_PX = 0.5
SETTINGS = WindowSettings(
    window=3, gate_chi2=tuple(float(chi2.ppf(0.99, max(d, 1))) for d in range(20))
)


def _poses(n: int, rng: np.random.Generator) -> np.ndarray:
    """n poses (p, Psi) of a UAV 60 m up flying north, slightly tilted."""
    p = np.column_stack([np.arange(n) * 4.0, rng.normal(0, 0.5, n), np.full(n, -60.0)])
    return np.column_stack([p, rng.normal(0, 0.03, (n, 2)), 0.2 + rng.normal(0, 0.03, n)])


def _ground_points(k: int, rng: np.random.Generator) -> np.ndarray:
    return np.column_stack([rng.uniform(0, 12, k), rng.uniform(-15, 15, k), rng.normal(0, 2, k)])


def _state_with_clones(
    poses: np.ndarray, rng: np.random.Generator, var: float = 1e-4
) -> tuple[JointState, list]:
    x0 = np.concatenate([poses[-1, :3], np.zeros(3), poses[-1, 3:]])
    st = JointState([("uav", INS, x0, np.eye(9) * 1e-4)], coordinates("cartesian"))
    keys = []
    for pose in poses:
        A = rng.normal(size=(6, 6))
        P = var * (A @ A.T / 6 + np.eye(6))
        key, _ = st.add_anchor(pose, P, np.zeros((6, st.n)), True)
        keys.append(key)
    return st, keys


def _observe(poses: np.ndarray, f: np.ndarray, rng: np.random.Generator, noise: float) -> tuple:
    track, clone, z = [], [], []
    for c, pose in enumerate(poses):
        zc, _, _ = OBS.predict(pose[:3], pose[3:], f)
        for j in range(len(f)):
            track.append(j)
            clone.append(c)
            z.append(zc[j] + rng.normal(0, noise, 4))
    order = np.lexsort((clone, track))
    return np.array(track)[order], np.array(clone)[order], np.array(z)[order]


def test_point_fit_recovers_the_point_from_a_rough_guess() -> None:
    rng = np.random.default_rng(0)
    poses = _poses(4, rng)
    f = _ground_points(10, rng)
    track, clone, z = _observe(poses, f, rng, 0.0)
    guess = f + rng.normal(0, 1.5, f.shape)  # metres off, as a far stereo point is
    t = TrackObservations(track, clone, z, guess)
    fitted = fit_points(OBS, poses, t, clone, iterations=5)
    np.testing.assert_allclose(fitted, f, atol=1e-6)


def test_null_space_residuals_vanish_at_the_truth_and_ignore_the_point_guess() -> None:
    """At the true clone poses with exact observations r0 = 0; with a perturbed point guess
    the fit absorbs it (the point's error is projected out, not passed to the poses)."""
    rng = np.random.default_rng(1)
    poses = _poses(4, rng)
    st, keys = _state_with_clones(poses, rng)
    f = _ground_points(8, rng)
    track, clone, z = _observe(poses, f, rng, 0.0)
    t = TrackObservations(track, np.array(keys)[clone], z, f + rng.normal(0, 0.5, f.shape))
    R = np.eye(4) * SIGMA_PX**2
    res = track_residuals(OBS, st, t, R, SETTINGS)
    assert res.used == 8 and res.rejected == 0
    assert res.H.shape == (len(res.r), 6 * 4)
    np.testing.assert_allclose(res.r, 0.0, atol=1e-7)


def test_null_space_residuals_see_a_pose_error_and_are_white() -> None:
    """With noisy observations at the truth the (compressed) residual's whitened square
    follows chi-square with its dof; moving one clone off its truth shows in r0 ~ H0 dx."""
    rng = np.random.default_rng(2)
    poses = _poses(4, rng)
    st, keys = _state_with_clones(poses, rng)
    stats = []
    for _ in range(40):
        f = _ground_points(6, rng)
        track, clone, z = _observe(poses, f, rng, SIGMA_PX)
        t = TrackObservations(track, np.array(keys)[clone], z, f)
        res = track_residuals(OBS, st, t, np.zeros((4, 4)) + np.eye(4) * SIGMA_PX**2, SETTINGS)
        stats.append((res.r @ res.r / SIGMA_PX**2, len(res.r)))
    d2, dof = np.array(stats).T
    assert abs(d2.sum() / dof.sum() - 1.0) < 0.15  # r0 white with sigma^2 (~2 % gated out)
    # a 5 cm shift of the second clone: the linear prediction H0 dx explains r0
    f = _ground_points(6, rng)
    track, clone, z = _observe(poses, f, rng, 0.0)
    dx = np.zeros(6)
    dx[:3] = [0.05, -0.03, 0.02]
    rows = st.anchor_rows(keys[1])
    st.x[rows] = poses[1] - dx  # the state's clone is off by -dx: z sees the truth
    t = TrackObservations(track, np.array(keys)[clone], z, f)
    res = track_residuals(OBS, st, t, np.eye(4) * SIGMA_PX**2, SETTINGS)
    pred = res.H[:, 6:12] @ dx
    assert np.linalg.norm(res.r - pred) < 0.05 * np.linalg.norm(pred)


def test_a_wrong_observation_is_gated_out() -> None:
    rng = np.random.default_rng(3)
    poses = _poses(4, rng)
    st, keys = _state_with_clones(poses, rng, var=1e-6)  # clones known to 1 mm / 1 mrad
    f = _ground_points(5, rng)
    track, clone, z = _observe(poses, f, rng, SIGMA_PX)
    z = z.copy()
    z[(track == 2) & (clone == 1)] += [25.0, -12.0, 25.0, -12.0]  # another point's pixels
    t = TrackObservations(track, np.array(keys)[clone], z, f)
    res = track_residuals(OBS, st, t, np.eye(4) * SIGMA_PX**2, SETTINGS)
    assert res.rejected == 1 and res.used == 4


def test_pinned_clones_stay_until_released_and_while_a_landmark_refers_to_them() -> None:
    rng = np.random.default_rng(4)
    st, keys = _state_with_clones(_poses(3, rng), rng)
    n_clones = 9 + 18
    assert st.n == n_clones
    st.remove_landmarks(np.zeros(0, dtype=np.int64))  # no landmark refers to them: kept
    assert [st.anchor_rows(k) is not None for k in keys] == [True] * 3
    x_before = st.x.copy()
    st.release_anchor(keys[0])
    assert st.anchor_rows(keys[0]) is None and st.n == n_clones - 6
    np.testing.assert_array_equal(st.x, x_before[np.r_[0:9, 15:27]])
    # a clone that anchors a landmark outlives its release until the landmark goes
    st.add_landmarks(np.array([[0.1, 0.2, 0.03]]), np.eye(3), np.zeros((3, st.n)), keys[1])
    st.release_anchor(keys[1])
    assert st.anchor_rows(keys[1]) is not None
    st.remove_landmarks(np.array([0]))
    assert st.anchor_rows(keys[1]) is None and st.anchor_rows(keys[2]) is not None


class _Frame:
    def __init__(self, z: np.ndarray, desc: np.ndarray) -> None:
        self.z, self.desc = z, desc


def test_track_book_keeps_each_tracks_observations_in_order() -> None:
    rng = np.random.default_rng(5)
    book = TrackBook()
    desc = rng.integers(0, 255, (4, 128), dtype=np.uint8)
    z0 = rng.normal(size=(4, 4))
    book.start(np.arange(4), 10, _Frame(z0, desc), np.zeros((4, 3)), np.tile(np.eye(3), (4, 1, 1)))
    z1 = rng.normal(size=(2, 4))
    book.extend(
        np.array([1, 3]), np.array([0, 1]), 11, _Frame(z1, desc[[1, 3]]), np.ones((2, 3)),
        np.tile(np.eye(3), (2, 1, 1)),
    )  # fmt: skip
    assert book.lengths().tolist() == [1, 2, 1, 2]
    assert book.first_clones().tolist() == [10, 10, 10, 10]
    taken = book.take(np.array([True, True, False, True]))
    # track 0 (one observation) is dropped unused; tracks 1 and 3 come back, in time order
    assert taken.n_tracks == 2 and len(book) == 1
    assert taken.track.tolist() == [0, 0, 1, 1] and taken.clone.tolist() == [10, 11, 10, 11]
    np.testing.assert_array_equal(taken.z, np.stack([z0[1], z1[0], z0[3], z1[1]]))
    np.testing.assert_array_equal(taken.m, np.ones((2, 3)))


def _ended_tracks(poses: np.ndarray, rng: np.random.Generator) -> TrackObservations:
    f = _ground_points(12, rng)
    track, clone, z = _observe(poses, f, rng, SIGMA_PX)
    return TrackObservations(track, clone, z, f + rng.normal(0, 0.3, f.shape))


class _Vehicle:  # what the window's residuals need of a VehicleInput
    obs = OBS


def test_pending_rows_wait_for_their_clones_columns_and_release_leaving_clones_after() -> None:
    """The rows of ended tracks, applied later (`pending_rows` / `flush`), are the update
    applied at once, on the clones' columns as they are when applied (here after an earlier
    anchor left and moved them); a clone leaving the window stays until they are applied."""
    rng = np.random.default_rng(7)
    poses = _poses(4, rng)
    st, keys = _state_with_clones(poses, rng)
    keys_c = keys[1:]
    t = _ended_tracks(poses[1:], rng)
    t = TrackObservations(t.track, np.asarray(keys_c)[t.clone], t.z, t.m)
    ekf = FilterSettings("ekf")
    window = SlidingWindow(st, SETTINGS, ekf, GammaPolicy(ekf), np.eye(4) * SIGMA_PX**2)
    window._residuals(_Vehicle(), t)
    window._leaving.append(keys_c[0])
    window._frame_of[keys_c[0]] = ("uav1", 1_000)  # as `step` registers the clones it makes
    st.release_anchor(keys[0])  # the columns of the other clones move by 6
    # the same rows applied at once, on a copy of the state as it is now
    ref = copy.deepcopy(st)
    tr = track_residuals(OBS, ref, t, np.eye(4) * SIGMA_PX**2, SETTINGS)
    cols = np.concatenate([ref.anchor_rows(int(k)) for k in tr.clone_keys])
    ref.update(ekf, GammaPolicy(ekf), tr.r, np.zeros(len(tr.r)), tr.H, cols,
               SIGMA_PX**2 * np.eye(len(tr.r)))  # fmt: skip
    assert st.anchor_rows(keys_c[0]) is not None  # waits for the rows that use it
    rows = window.pending_rows()
    assert rows is not None and len(rows.r) == len(tr.r) and tr.used == 12
    # a run stopped before the rows are applied (a divergence) still has the leaving clone
    assert [lp.stamp_ns for lp in window.in_window()] == [1_000]
    window.flush(())
    assert window.pending_rows() is None and st.anchor_rows(keys_c[0]) is None
    # the leaving clone's pose as the update left it, then released
    (lagged,) = window.take_lagged()
    leaving = ref.anchor_rows(keys_c[0])
    assert (lagged.vehicle, lagged.stamp_ns) == ("uav1", 1_000) and not window.take_lagged()
    np.testing.assert_allclose(lagged.pose, ref.x[leaving], rtol=0, atol=1e-12)
    np.testing.assert_allclose(lagged.cov, ref.P[np.ix_(leaving, leaving)], rtol=0, atol=1e-15)
    ref.release_anchor(keys_c[0])
    np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-15)
    assert not np.allclose(st.x[9:], poses[2:].ravel())  # the update did move the clones


def test_rows_stacked_into_a_landmark_update_equal_two_ekf_updates() -> None:
    """`VisualUpdater.update` with extra linear rows (the window's) is, for the EKF, the
    landmark update followed by an update with those rows (their innovation moved by the
    first update's correction): one pass over P instead of two."""
    rng = np.random.default_rng(8)
    poses = _poses(3, rng)
    st, keys = _state_with_clones(poses, rng)
    k = 3
    slots = st.add_landmarks(_ground_points(k, rng), np.eye(3 * k) * 0.04, np.zeros((3 * k, st.n)))
    A = rng.normal(size=(st.n, st.n))
    st.P[...] = A @ A.T / st.n * 1e-3 + np.eye(st.n) * 1e-4
    d = st.landmark_columns(slots).shape[1]
    pred = LandmarkPrediction(
        slots, rng.normal(300, 50, (k, 4)), rng.normal(0, 30, (k, 4, 9)),
        rng.normal(0, 30, (k, 4, d)), np.zeros((k, 4, 4)),
    )  # fmt: skip
    z = pred.z + rng.normal(0, SIGMA_PX, (k, 4))
    cols = np.concatenate([st.anchor_rows(int(key)) for key in keys[:2]])
    extra = ExtraRows(
        rng.normal(0, 0.5, 7), rng.normal(0, 30, (7, 12)), cols, SIGMA_PX**2 * np.eye(7)
    )
    ekf = FilterSettings("ekf")
    v_idx = np.arange(9)
    one = copy.deepcopy(st)
    VisualUpdater(one, ekf, SIGMA_PX).update(v_idx, pred, np.arange(k), z, (), extra)
    two = copy.deepcopy(st)
    up = VisualUpdater(two, ekf, SIGMA_PX)
    up.update(v_idx, pred, np.arange(k), z, ())
    r = extra.r - extra.H @ (two.x[cols] - st.x[cols])
    two.update(ekf, up.gamma, r, np.zeros(7), extra.H, extra.cols, extra.R)
    np.testing.assert_allclose(one.x, two.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(one.P, two.P, rtol=0, atol=1e-12)
    assert not np.allclose(one.x, st.x)
