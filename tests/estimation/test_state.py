"""The joint state: structured predict and landmark augmentation/marginalisation equal the
dense formulas; the in-place update equals the pure reference updates; motion segments;
association and spreading."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from cvslam_cli.estimation.association import (
    LandmarkPrediction,
    associate,
    spread_order,
)
from cvslam_cli.estimation.filters import UpdateResult, ekf_update, hinf_update
from cvslam_cli.estimation.motion import InsNoise
from cvslam_cli.estimation.motion_models import InsModel, OdometryModel
from cvslam_cli.estimation.slam import motion_segments
from cvslam_cli.estimation.state import FilterSettings, JointState

RNG = np.random.default_rng(11)


def _spd(n: int) -> np.ndarray:
    A = RNG.normal(size=(n, n))
    return A @ A.T / n + 0.1 * np.eye(n)


def _state() -> JointState:
    ins = InsModel(InsNoise(2e-3, 1.7e-4, 3e-3, 2e-5), biases=True)
    odo = OdometryModel(0.05, 0.01, z_nav_m=0.0)
    st = JointState(
        [("a", ins, RNG.normal(size=15), _spd(15)), ("b", odo, RNG.normal(size=3), _spd(3))]
    )
    k = 5
    n = st.n
    J = RNG.normal(size=(3 * k, n))
    P_mx = J @ st.P
    P_mm = J @ st.P @ J.T + _spd(3 * k)
    st.add_landmarks(RNG.normal(size=(k, 3)), P_mm, P_mx)
    return st


def test_augmentation_keeps_a_valid_joint_covariance():
    st = _state()
    assert st.n == 18 + 15 and st.n_landmarks == 5
    assert np.allclose(st.P, st.P.T)
    assert np.linalg.eigvalsh(st.P)[0] > 0


def test_block_predict_equals_the_dense_transition():
    st = _state()
    P0, x0 = st.P.copy(), st.x.copy()
    F = np.eye(15) + 0.1 * RNG.normal(size=(15, 15))
    Q = _spd(15) * 0.01
    x_new = RNG.normal(size=15)
    st.predict("a", x_new, F, Q)
    F_full = np.eye(st.n)
    F_full[:15, :15] = F
    Q_full = np.zeros((st.n, st.n))
    Q_full[:15, :15] = Q
    np.testing.assert_allclose(st.P, F_full @ P0 @ F_full.T + Q_full, atol=1e-12)
    np.testing.assert_allclose(st.x[15:], x0[15:])
    np.testing.assert_allclose(st.x[:15], x_new)


def test_removing_landmarks_is_marginalisation_and_storage_grows():
    st = _state()
    P0, x0 = st.P.copy(), st.x.copy()
    kept = st.remove_landmarks(np.array([1, 3]))
    assert list(kept) == [0, 2, 4]
    idx = np.r_[np.arange(18), 18 + np.r_[0:3, 6:9, 12:15]]
    np.testing.assert_array_equal(st.P, P0[np.ix_(idx, idx)])
    np.testing.assert_array_equal(st.x, x0[idx])
    # many more landmarks than the initial storage
    for _ in range(40):
        n = st.n
        st.add_landmarks(np.zeros((3, 3)), np.eye(9), np.zeros((9, n)))
    assert st.n_landmarks == 123 and st.P.shape == (st.n, st.n)
    np.testing.assert_array_equal(st.P[:18, :18], P0[:18, :18])


def _reference(st: JointState, s: FilterSettings, y, h, H, cols, R) -> UpdateResult:
    """The pure update of the state as it is now (with the bound the state carries)."""
    x, P = st.x.copy(), st.P.copy()
    if s.kind == "ekf":
        return ekf_update(x, P, y, h, H, R, cols=cols)
    bounded = None if s.bound == "all" else np.arange(st.n_vehicle_states)
    gamma = st.gamma if st.gamma is not None else s.gamma
    return hinf_update(x, P, y, h, H, s.r_scale * R, gamma, bounded, s.gamma_margin, cols)


# (settings, whether gamma gets raised in the sequence below)
SETTINGS = [
    (FilterSettings(kind="ekf"), False),
    (FilterSettings(kind="hinf", gamma=10.0, bound="vehicle"), False),
    (FilterSettings(kind="hinf", gamma=10.0, bound="all", c_v=1.5), True),  # landmarks outgrow it
    (FilterSettings(kind="hinf", gamma=0.05, bound="vehicle"), True),  # at the first update
    (FilterSettings(kind="hinf", gamma=0.05, bound="all"), True),
    (FilterSettings(kind="hinf", gamma=np.inf, bound="vehicle"), False),  # the EKF posterior
]


def test_in_place_update_equals_the_pure_update_while_the_state_grows_and_shrinks():
    """JointState.update works on its own storage; over a sequence of predicts, updates of
    one vehicle and a few landmarks (a `cols` subset), landmarks added past the storage's
    capacity (it reallocates) and removed, it gives the pure `ekf_update` / `hinf_update`
    result of the state before each update, to 1e-12 of the covariance's scale (in
    practice bit for bit), keeps P exactly symmetric and positive definite, and persists
    a raised gamma exactly as before. One BLAS thread, as the fuse stage runs the filter."""
    with threadpool_limits(limits=1, user_api="blas"):
        for s, raises in SETTINGS:
            _in_place_sequence(s, raises)


def _in_place_sequence(s: FilterSettings, raises: bool) -> None:
    rng = np.random.default_rng(23)

    def spd(n: int) -> np.ndarray:
        A = rng.normal(size=(n, n))
        return A @ A.T / n + 0.1 * np.eye(n)

    ins = InsModel(InsNoise(2e-3, 1.7e-4, 3e-3, 2e-5), biases=True)
    odo = OdometryModel(0.05, 0.01, z_nav_m=0.0)
    st = JointState(
        [("a", ins, rng.normal(size=15), spd(15)), ("b", odo, rng.normal(size=3), spd(3))]
    )
    raised_seen = 0
    for step in range(40):
        if step % 4 == 0:  # grow: 12 landmarks correlated with the state
            k, n = 12, st.n
            J = 0.3 * rng.normal(size=(3 * k, n))
            st.add_landmarks(rng.normal(size=(k, 3)), J @ st.P @ J.T + spd(3 * k), J @ st.P)
        if step % 7 == 6:  # shrink
            st.remove_landmarks(rng.choice(st.n_landmarks, size=5, replace=False))
        vname = "a" if step % 2 else "b"
        vb = st.vehicles[vname]
        F = np.eye(vb.model.n) + 0.05 * rng.normal(size=(vb.model.n, vb.model.n))
        st.predict(vname, st.vehicle_x(vname) + 0.1, F, 0.01 * spd(vb.model.n))
        slots = np.sort(rng.choice(st.n_landmarks, size=4, replace=False))
        cols = np.concatenate([vb.index, st.landmark_index(slots).ravel()])
        m = 8
        H = rng.normal(size=(m, len(cols)))
        R = np.diag(rng.uniform(0.5, 2.0, m))
        y, h = rng.normal(size=m), rng.normal(size=m)
        ref = _reference(st, s, y, h, H, cols, R)
        gamma_before = st.gamma
        res = st.update(s, y, h, H, cols, R)
        scale = np.abs(ref.P).max()
        np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12 * np.abs(ref.x).max())
        assert res.nis == ref.nis
        assert res.gamma == ref.gamma and res.gamma_raised == ref.gamma_raised
        assert st.gamma == (res.gamma if res.gamma_raised else gamma_before)
        assert np.shares_memory(res.P, st.P) and np.shares_memory(res.x, st.x)
        np.testing.assert_array_equal(st.P, st.P.T)
        assert np.linalg.eigvalsh(st.P)[0] > 0
        raised_seen += res.gamma_raised
    assert st.n_landmarks > 64  # grew past the initial storage
    if raises:
        assert raised_seen >= 1 and st.gamma is not None and st.gamma > s.gamma
    else:
        assert raised_seen == 0 and st.gamma is None


def test_motion_segments_hold_each_sample_until_the_next():
    stamps = np.array([0, 10, 20, 30], dtype=np.int64) * 1_000_000
    U = np.arange(4, dtype=float)[:, None] * np.ones((1, 2))
    u, dts = motion_segments(stamps, U, 5_000_000, 25_000_000)
    np.testing.assert_allclose(dts, [5e-3, 10e-3, 5e-3])
    np.testing.assert_allclose(u[:, 0], [0, 1, 2])
    u, dts = motion_segments(stamps, U, 0, 0)
    assert len(dts) == 0
    # before the first sample: the first one; no samples (constant velocity): one step
    u, dts = motion_segments(stamps, U, -5_000_000, 5_000_000)
    np.testing.assert_allclose(u[:, 0], [0, 0])
    u, dts = motion_segments(np.zeros(0, dtype=np.int64), np.zeros((0, 0)), 0, 100_000_000)
    assert u.shape == (1, 0) and np.allclose(dts, [0.1])


def _prediction(z: np.ndarray, sigma: float = 1.0) -> LandmarkPrediction:
    k = len(z)
    S = np.broadcast_to(np.eye(4) * sigma**2, (k, 4, 4)).copy()
    return LandmarkPrediction(np.arange(k), z, np.zeros((k, 4, 1)), np.zeros((k, 4, 3)), S)


def test_association_gates_then_takes_the_closest_distinctive_descriptor():
    z = np.array([[100, 100, 90, 100], [300, 200, 280, 200], [500, 300, 490, 300.0]])
    desc_lm = RNG.integers(0, 255, size=(3, 128)).astype(np.uint8)
    # matches: landmark 0 seen (noisy desc) + a look-alike far outside its window;
    # landmark 1 seen twice inside its window with two similar descriptors (ambiguous);
    # landmark 2 not seen; one unrelated match
    z_obs = np.array(
        [
            [100.5, 99.5, 90.2, 99.6],
            [600, 100, 590, 100.0],
            [300.5, 200.2, 280.3, 200.0],
            [299.6, 200.4, 279.8, 200.2],
            [50, 400, 40, 400.0],
        ]
    )
    noise = lambda: RNG.integers(-3, 4, size=128)  # noqa: E731
    d = np.clip(
        np.stack(
            [
                desc_lm[0] + noise(),
                desc_lm[0] + noise(),
                desc_lm[1] + noise(),
                desc_lm[1] + noise(),
                RNG.integers(0, 255, 128),
            ]
        ),
        0,
        255,
    ).astype(np.uint8)
    a = associate(_prediction(z), desc_lm, z_obs, d, gate_chi2=18.47, ratio=0.8, max_distance=350)
    assert list(a.pred_index) == [0] and list(a.match_index) == [0]
    assert list(a.near_landmark) == [True, False, True, True, False]


def test_a_match_goes_to_one_landmark_only():
    z = np.array([[100, 100, 90, 100], [101, 100, 91, 100.0]])
    desc_lm = RNG.integers(0, 255, size=(2, 128)).astype(np.uint8)
    d = np.clip(desc_lm[1].astype(int) + 2, 0, 255).astype(np.uint8)[None]
    a = associate(_prediction(z, 2.0), desc_lm, np.array([[100.5, 100, 90.5, 100]]), d,
                  gate_chi2=18.47, ratio=0.8, max_distance=1e9)  # fmt: skip
    assert list(a.pred_index) == [1] and list(a.match_index) == [0]


def test_spread_order_visits_every_cell_before_repeating():
    uv = np.column_stack([RNG.uniform(0, 400, 200), RNG.uniform(0, 400, 200)])
    prio = RNG.uniform(size=200)
    order = spread_order(uv, prio, (400, 400), grid=4)
    assert sorted(order) == list(range(200))
    cells = (uv[order, 1] // 100).astype(int) * 4 + (uv[order, 0] // 100).astype(int)
    assert len(set(cells[:16])) == 16
    # within a cell, lower priority first
    c0 = order[cells == cells[0]]
    assert np.all(np.diff(prio[c0]) >= 0)
