"""The joint state: structured predict and landmark augmentation/marginalisation equal the
dense formulas; the in-place update equals the pure reference updates; NH-infinity's bound
on a chosen set of vehicles (`JointState.update(vehicles=...)`): the vehicles whose pose is
known; none bounded is the EKF with R_hat."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits

from cvslam_cli.estimation.filters import (
    FilterSettings,
    GammaPolicy,
    UpdateResult,
    ekf_update,
    hinf_update,
)
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import InsModel, OdometryModel
from cvslam_cli.estimation.state import JointState, _compact

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
    kept = st.remove_landmarks(np.zeros(0, dtype=np.int64))  # nothing leaves
    assert list(kept) == [0, 1, 2, 3, 4] and st.n == len(x0)
    np.testing.assert_array_equal(st.P, P0)
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


def test_in_place_compaction_equals_the_gather():
    """`_compact` moves the kept rows and columns to the front of a larger storage in place:
    the same numbers as the gather for masks that drop the first row, the last, single rows
    between long runs and long runs between single rows; the storage beyond is untouched."""
    for keep in (
        np.r_[False, np.ones(40, bool)],
        np.r_[np.ones(40, bool), False],
        RNG.random(41) < 0.9,
        RNG.random(41) < 0.3,
        np.tile([True, True, False], 14)[:41],
    ):
        store = RNG.normal(size=(50, 50))
        x_store = RNG.normal(size=50)
        P, x = store[:41, :41].copy(), x_store[:41].copy()
        beyond, x_beyond = store[:, 41:].copy(), x_store[41:].copy()
        _compact(store, x_store, keep)
        k = int(keep.sum())
        np.testing.assert_array_equal(store[:k, :k], P[np.ix_(keep, keep)])
        np.testing.assert_array_equal(x_store[:k], x[keep])
        np.testing.assert_array_equal(store[:, 41:], beyond)
        np.testing.assert_array_equal(x_store[41:], x_beyond)


def _reference(
    st: JointState, s: FilterSettings, gamma: GammaPolicy, y, h, H, cols, R
) -> UpdateResult:
    """The pure update of the state as it is now (with the bound the policy holds)."""
    x, P = st.x.copy(), st.P.copy()
    if s.kind == "ekf":
        return ekf_update(x, P, y, h, H, R, cols=cols)
    bounded = None if s.bound == "all" else np.arange(st.n_vehicle_states)
    return hinf_update(x, P, y, h, H, s.r_scale * R, gamma.gamma, bounded, s.gamma_margin, cols)


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
    policy = GammaPolicy(s)
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
        ref = _reference(st, s, policy, y, h, H, cols, R)
        gamma_before = policy.raised
        res = st.update(s, policy, y, h, H, cols, R)
        scale = np.abs(ref.P).max()
        np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12 * np.abs(ref.x).max())
        assert res.nis == ref.nis
        assert res.gamma == ref.gamma and res.gamma_raised == ref.gamma_raised
        assert policy.raised == (res.gamma if res.gamma_raised else gamma_before)
        assert np.shares_memory(res.P, st.P) and np.shares_memory(res.x, st.x)
        np.testing.assert_array_equal(st.P, st.P.T)
        assert np.linalg.eigvalsh(st.P)[0] > 0
        raised_seen += res.gamma_raised
    assert st.n_landmarks > 64  # grew past the initial storage
    if raises:
        assert raised_seen >= 1 and policy.raised is not None and policy.raised > s.gamma
        assert policy.raised_count == raised_seen
    else:
        assert raised_seen == 0 and policy.raised is None and policy.raised_count == 0


def _observation(st):
    cols = np.concatenate([np.arange(15), st.landmark_index(np.array([1, 3])).ravel()])
    H = RNG.normal(size=(8, len(cols)))
    y, h = RNG.normal(size=8), RNG.normal(size=8)
    return y, h, H, cols, np.eye(8) * 0.3


def test_the_bound_is_on_the_given_vehicles_only():
    s = FilterSettings("hinf", gamma=1.5, c_v=1.2)
    for vehicles, bounded in (
        (["a"], np.arange(15)),
        (["b"], np.arange(15, 18)),
        (None, np.arange(18)),
    ):
        st = _state()
        y, h, H, cols, R = _observation(st)
        ref = hinf_update(st.x.copy(), st.P.copy(), y, h, H, s.r_scale * R, s.gamma,
                          bounded=bounded, margin=s.gamma_margin, cols=cols)  # fmt: skip
        res = st.update(s, GammaPolicy(s), y, h, H, cols, R, vehicles=vehicles)
        assert res.gamma == ref.gamma and res.gamma_raised == ref.gamma_raised
        np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12)


def test_the_observer_bound_is_on_the_observing_vehicle_only():
    """bound "observer": of the given vehicles, only those whose states the observation
    touches (vehicle a here: H's columns are a's and two landmarks'); none touched is the
    EKF with R_hat."""
    s = FilterSettings("hinf", gamma=1.5, c_v=1.2, bound="observer")
    for vehicles, bounded in ((None, np.arange(15)), (["a", "b"], np.arange(15)), (["b"], None)):
        st = _state()
        y, h, H, cols, R = _observation(st)
        if bounded is None:
            ref = ekf_update(st.x.copy(), st.P.copy(), y, h, H, s.r_scale * R, cols=cols)
        else:
            ref = hinf_update(st.x.copy(), st.P.copy(), y, h, H, s.r_scale * R, s.gamma,
                              bounded=bounded, margin=s.gamma_margin, cols=cols)  # fmt: skip
        st.update(s, GammaPolicy(s), y, h, H, cols, R, vehicles=vehicles)
        np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12)


def test_no_vehicle_bounded_is_the_ekf_with_the_scaled_noise():
    s = FilterSettings("hinf", gamma=1.5, c_v=1.2)
    st = _state()
    y, h, H, cols, R = _observation(st)
    ref = ekf_update(st.x.copy(), st.P.copy(), y, h, H, s.r_scale * R, cols=cols)
    st.update(s, GammaPolicy(s), y, h, H, cols, R, vehicles=[])
    np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12)
