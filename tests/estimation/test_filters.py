"""EKF and NH-infinity updates: NH-inf -> EKF as gamma -> inf, the Riccati form, existence;
the in-place variants equal the pure functions."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.filters import (
    BlockRows,
    FilterSettings,
    GammaPolicy,
    UpdateResult,
    _mirror_upper,
    _solve_right_lower_t,
    _syrk_upper,
    ekf_update,
    ekf_update_inplace,
    hinf_update,
    hinf_update_block_form,
    hinf_update_inplace,
    update_inplace,
)

RNG = np.random.default_rng(5)


def _problem(n=30, m=8):
    A = RNG.normal(size=(n, n))
    P = A @ A.T / n + 0.1 * np.eye(n)
    H = RNG.normal(size=(m, n))
    R = np.diag(RNG.uniform(0.5, 2.0, m))
    x = RNG.normal(size=n)
    y, h = RNG.normal(size=m), RNG.normal(size=m)
    return x, P, y, h, H, R


def test_hinf_equals_ekf_as_gamma_grows():
    x, P, y, h, H, R = _problem()
    ekf = ekf_update(x, P, y, h, H, R)
    for bounded in (None, np.arange(9)):
        hinf = hinf_update(x, P, y, h, H, R, gamma=1e7, bounded=bounded)
        np.testing.assert_allclose(hinf.x, ekf.x, atol=1e-9)
        np.testing.assert_allclose(hinf.P, ekf.P, atol=1e-9)
        assert not hinf.gamma_raised
        inf = hinf_update(x, P, y, h, H, R, gamma=np.inf, bounded=bounded)
        np.testing.assert_allclose(inf.P, ekf.P, atol=1e-9)
    assert ekf.nis > 0


def test_hinf_is_the_riccati_posterior_and_more_cautious():
    x, P, y, h, H, R = _problem()
    bounded = np.arange(9)
    gamma = 3.0
    res = hinf_update(x, P, y, h, H, R, gamma=gamma, bounded=bounded)
    assert not res.gamma_raised
    L = np.eye(len(x))[bounded]
    expected = np.linalg.inv(np.linalg.inv(P) + H.T @ np.linalg.inv(R) @ H - L.T @ L / gamma**2)
    np.testing.assert_allclose(res.P, expected, rtol=1e-8, atol=1e-10)
    ekf = ekf_update(x, P, y, h, H, R)
    # the H-infinity covariance is larger (more cautious) than the EKF's, and still SPD
    assert np.all(np.linalg.eigvalsh(res.P - ekf.P) > -1e-12)
    assert np.all(np.linalg.eigvalsh(res.P) > 0)


def test_existence_failure_raises_gamma_visibly():
    x, P, y, h, H, R = _problem()
    res = hinf_update(x, P, y, h, H, R, gamma=0.01, bounded=np.arange(9))
    assert res.gamma_raised and res.gamma > 0.01
    assert np.all(np.linalg.eigvalsh(res.P) > 0)
    assert np.allclose(res.P, res.P.T)


def test_covariance_stays_spd_over_many_updates():
    x, P, _, _, _, _ = _problem(n=20, m=4)
    for _ in range(300):
        H = RNG.normal(size=(4, 20))
        R = 0.5 * np.eye(4)
        res = hinf_update(
            x, P, RNG.normal(size=4), np.zeros(4), H, R, gamma=5.0, bounded=np.arange(6)
        )
        x, P = res.x, res.P + 0.01 * np.eye(20)  # a little process noise each step
        assert np.allclose(P, P.T) and np.linalg.eigvalsh(P)[0] > 0


def test_hinf_equals_the_papers_block_form():
    """The fast forms (pure and in place) equal the paper's corrector with the block matrix
    Sigma (`hinf_update_block_form`, the readable reference)."""
    x, P, y, h, H, R = _problem()
    for bounded in (np.arange(9), np.arange(30)):
        ref = hinf_update_block_form(x, P, y, h, H, R, 4.0, bounded)
        res = hinf_update(x, P, y, h, H, R, gamma=4.0, bounded=bounded)
        assert not res.gamma_raised
        np.testing.assert_allclose(res.P, ref.P, atol=1e-10)
        np.testing.assert_allclose(res.x, ref.x, atol=1e-10)
        assert abs(res.nis - ref.nis) < 1e-9 * ref.nis
        xv, Pv, work = _storage(x, P)
        hinf_update_inplace(xv, Pv, y, h, H, R, 4.0, bounded, 0.1, None, work)
        np.testing.assert_allclose(Pv, ref.P, atol=1e-10)
        np.testing.assert_allclose(xv, ref.x, atol=1e-10)


def test_sparse_columns_equal_the_dense_jacobian():
    x, P, y, h, _, R = _problem()
    cols = np.array([0, 1, 2, 17, 18, 19, 25])
    Hs = RNG.normal(size=(len(y), len(cols)))
    H = np.zeros((len(y), len(x)))
    H[:, cols] = Hs
    for a, b in (
        (ekf_update(x, P, y, h, H, R), ekf_update(x, P, y, h, Hs, R, cols=cols)),
        (
            hinf_update(x, P, y, h, H, R, 3.0, np.arange(9)),
            hinf_update(x, P, y, h, Hs, R, 3.0, np.arange(9), cols=cols),
        ),
    ):
        np.testing.assert_allclose(a.x, b.x, atol=1e-12)
        np.testing.assert_allclose(a.P, b.P, atol=1e-12)
        assert abs(a.nis - b.nis) < 1e-9


def test_block_rows_give_the_dense_update():
    """H = [H_v | blockdiag(H_1 .. H_k)] (update.py's stacked observations, anchors shared
    by several landmarks): P H^T from the blocks equals the dense product, and the in-place
    updates with `blocks` equal those without, to rounding."""
    x, P, y, h, _, R = _problem(n=40, m=12)
    k, r, d, nv = 3, 4, 5, 6
    lm = np.array([[6, 7, 8, 20, 21], [6, 7, 8, 30, 31], [10, 11, 12, 35, 36]])  # 6-8 shared
    cols = np.concatenate([np.arange(nv), lm.ravel()])
    Hb = RNG.normal(size=(k, r, d))
    H = np.zeros((k * r, nv + k * d))
    H[:, :nv] = RNG.normal(size=(k * r, nv))
    for j in range(k):
        H[r * j : r * j + r, nv + d * j : nv + d * j + d] = Hb[j]
    blocks = BlockRows(nv, r, d)
    HP = blocks.HP(P, H, cols)
    np.testing.assert_allclose(HP, H @ P[cols], rtol=0, atol=1e-13)
    S = H @ P[np.ix_(cols, cols)] @ H.T
    np.testing.assert_allclose(blocks.HPHt(HP, H, cols), S, rtol=0, atol=1e-12)
    bounded = np.arange(nv)
    for with_blocks in (None, blocks):
        xv, Pv, work = _storage(x, P)
        res = hinf_update_inplace(xv, Pv, y, h, H, R, 4.0, bounded, 0.1, cols, work, with_blocks)
        ref = hinf_update(x, P, y, h, H, R, 4.0, bounded, 0.1, cols)
        np.testing.assert_allclose(Pv, ref.P, rtol=0, atol=1e-12 * np.abs(ref.P).max())
        np.testing.assert_allclose(xv, ref.x, rtol=0, atol=1e-12 * np.abs(ref.x).max())
        assert abs(res.nis - ref.nis) < 1e-9
        np.testing.assert_array_equal(Pv, Pv.T)
        xv, Pv, work = _storage(x, P)
        ekf_update_inplace(xv, Pv, y, h, H, R, cols, work, with_blocks)
        ref = ekf_update(x, P, y, h, H, R, cols)
        np.testing.assert_allclose(Pv, ref.P, rtol=0, atol=1e-12 * np.abs(ref.P).max())


def test_block_rows_with_a_tail_give_the_dense_product():
    """The sliding window's rows stacked after the landmarks' (`update.py`): a tail of rows
    touching only the last columns (here clone columns one landmark's anchor shares)."""
    _, P, _, _, _, _ = _problem(n=40, m=12)
    k, r, d, nv, t, mt = 2, 4, 5, 6, 6, 5
    lm = np.array([[6, 7, 8, 20, 21], [10, 11, 12, 35, 36]])
    cols = np.concatenate([np.arange(nv), lm.ravel(), np.arange(6, 12)])  # tail: 6..11
    H = np.zeros((k * r + mt, nv + k * d + t))
    H[: k * r, :nv] = RNG.normal(size=(k * r, nv))
    for j in range(k):
        H[r * j : r * j + r, nv + d * j : nv + d * j + d] = RNG.normal(size=(r, d))
    H[k * r :, nv + k * d :] = RNG.normal(size=(mt, t))
    got = BlockRows(nv, r, d, t).HP(P, H, cols)
    np.testing.assert_allclose(got, H @ P[cols], rtol=0, atol=1e-13)
    S = H @ P[np.ix_(cols, cols)] @ H.T
    np.testing.assert_allclose(BlockRows(nv, r, d, t).HPHt(got, H, cols), S, atol=1e-12)


def test_the_right_side_solve_is_the_left_sides_transpose_and_writes_only_when_asked():
    """V = B C^-T from the right (`_whitened`'s V = P H^T C^-T) equals (C^-1 B^T)^T; with
    `overwrite` a column-major B holds the result, without it B is left as it was."""
    _, P, _, _, H, _ = _problem(n=30, m=8)
    C = np.linalg.cholesky(H @ P @ H.T + np.eye(8))
    B = np.asfortranarray(P @ H.T)  # (n, m) column-major, as P H^T from H P's rows
    ref = np.linalg.solve(C, B.T).T
    before = B.copy()
    np.testing.assert_allclose(_solve_right_lower_t(C, B, overwrite=False), ref, atol=1e-12)
    np.testing.assert_array_equal(B, before)
    V = _solve_right_lower_t(C, B, overwrite=True)
    np.testing.assert_allclose(V, ref, atol=1e-12)
    assert np.shares_memory(V, B) and V.flags.f_contiguous


def test_joseph_form_equals_the_textbook_joseph_form():
    x, P, y, h, H, R = _problem()
    res = ekf_update(x, P, y, h, H, R)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    A = np.eye(len(x)) - K @ H
    np.testing.assert_allclose(res.P, A @ P @ A.T + K @ R @ K.T, atol=1e-10)
    np.testing.assert_allclose(res.x, x + K @ (y - h), atol=1e-10)


def _storage(x, P, extra=7):
    """x and P as views of larger storage (as JointState keeps them) and a work buffer."""
    n = len(x)
    xs, Ps = np.zeros(n + extra), np.zeros((n + extra, n + extra))
    xs[:n], Ps[:n, :n] = x, P
    return xs[:n], Ps[:n, :n], np.empty(2 * (n + extra) ** 2)[: 2 * n * n].reshape(2, n, n)


def test_in_place_updates_equal_the_pure_ones():
    x, P, y, h, H, R = _problem()
    cols = np.array([0, 1, 2, 4, 9, 17, 18, 19, 25])
    Hs = H[:, cols]
    for c, Hc in ((None, H), (cols, Hs)):
        ref = ekf_update(x, P, y, h, Hc, R, cols=c)
        xv, Pv, work = _storage(x, P)
        res = ekf_update_inplace(xv, Pv, y, h, Hc, R, c, work)
        assert res.P is Pv and res.x is xv
        np.testing.assert_allclose(Pv, ref.P, rtol=0, atol=1e-12 * np.abs(ref.P).max())
        np.testing.assert_allclose(xv, ref.x, rtol=0, atol=1e-12 * np.abs(ref.x).max())
        assert res.nis == ref.nis
        for bounded in (np.arange(9), None):
            for gamma in (4.0, 0.01, np.inf):  # 0.01: the existence condition fails
                ref = hinf_update(x, P, y, h, Hc, R, gamma, bounded, 0.1, c)
                xv, Pv, work = _storage(x, P)
                res = hinf_update_inplace(xv, Pv, y, h, Hc, R, gamma, bounded, 0.1, c, work)
                np.testing.assert_allclose(Pv, ref.P, rtol=0, atol=1e-12 * np.abs(ref.P).max())
                np.testing.assert_allclose(xv, ref.x, rtol=0, atol=1e-12 * np.abs(ref.x).max())
                assert res.nis == ref.nis and res.gamma == ref.gamma
                assert res.gamma_raised == (gamma == 0.01)
                np.testing.assert_array_equal(Pv, Pv.T)  # syrk: exactly symmetric


def test_in_place_update_rejects_a_work_buffer_that_overlaps_the_state():
    x, P, y, h, H, R = _problem()
    xv, Pv, work = _storage(x, P)
    with pytest.raises(ValueError, match="overlap"):
        n = len(x)
        flat = np.empty(2 * n * n)
        P_in_flat = flat[n * n :].reshape(n, n)
        P_in_flat[:] = P
        ekf_update_inplace(xv, P_in_flat, y, h, H, R, None, flat.reshape(2, n, n))
    with pytest.raises(ValueError, match="shape"):
        hinf_update_inplace(xv, Pv, y, h, H, R, 4.0, None, 0.1, None, work[0])


def test_syrk_updates_the_upper_triangle_of_a_view_where_it_lies():
    """The in-place update's rank-k step works on P inside the state's larger storage (rows
    longer than n): the upper triangle becomes P - A A^T, the lower one and the storage
    around P are left alone, and the mirror then makes it the symmetric result."""
    _, P, *_ = _problem(n=37)
    A = RNG.normal(size=(37, 5))
    storage = RNG.normal(size=(45, 45))
    view = storage[:37, :37]
    view[:] = P
    before = storage.copy()
    _syrk_upper(view, A, -1.0)
    iu = np.triu_indices(37)
    expected = P - A @ A.T
    np.testing.assert_allclose(view[iu], expected[iu], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.tril(view, -1), np.tril(P, -1))
    np.testing.assert_array_equal(storage[37:], before[37:])
    np.testing.assert_array_equal(storage[:, 37:], before[:, 37:])
    _mirror_upper(view)
    np.testing.assert_array_equal(view, view.T)
    np.testing.assert_allclose(view, expected, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="contiguous rows"):
        _syrk_upper(np.asfortranarray(P), A, -1.0)  # columns contiguous, not rows


def test_noise_scaling_of_eq_13_14_applies_to_nh_infinity_only():
    Q, R = np.diag([1.0, 2.0]), np.diag([3.0, 4.0])
    hinf = FilterSettings("hinf", c_w=1.5, c_v=2.0)
    np.testing.assert_array_equal(hinf.process_noise(Q), 2.25 * Q)
    np.testing.assert_array_equal(hinf.measurement_noise(R), 4.0 * R)
    ekf = FilterSettings("ekf", c_w=1.5, c_v=2.0)
    np.testing.assert_array_equal(ekf.process_noise(Q), Q)
    np.testing.assert_array_equal(ekf.measurement_noise(R), R)


def test_gamma_policy_keeps_a_raised_gamma_and_counts_the_raises():
    policy = GammaPolicy(FilterSettings("hinf", gamma=3.0, gamma_margin=0.5))
    assert policy.gamma == 3.0 and policy.raised is None and policy.margin == 0.5
    policy.record(UpdateResult(np.zeros(1), np.eye(1), 1.0, 3.0, False))
    assert policy.gamma == 3.0 and policy.raised_count == 0
    policy.record(UpdateResult(np.zeros(1), np.eye(1), 1.0, 7.0, True))
    assert policy.gamma == 7.0 and policy.raised_count == 1


def test_the_configured_update_uses_the_scaled_noise_and_the_policys_gamma():
    """`update_inplace`: EKF with R; NH-infinity with c_v^2 R and the policy's gamma, which
    it raises (and keeps) when the existence condition fails; no bounded state: the EKF
    with c_v^2 R."""
    x, P, y, h, H, R = _problem()
    bounded = np.arange(9)
    cases = [
        (FilterSettings("ekf", c_v=2.0), bounded, ekf_update(x, P, y, h, H, R)),
        (FilterSettings("hinf", gamma=4.0, c_v=2.0, gamma_margin=0.1), bounded,
         hinf_update(x, P, y, h, H, 4.0 * R, 4.0, bounded, 0.1)),
        (FilterSettings("hinf", gamma=4.0, c_v=2.0), np.zeros(0, np.int64),
         ekf_update(x, P, y, h, H, 4.0 * R)),
        (FilterSettings("hinf", gamma=0.01, gamma_margin=0.1), None,
         hinf_update(x, P, y, h, H, R, 0.01, None, 0.1)),
    ]  # fmt: skip
    for settings, bnd, ref in cases:
        policy = GammaPolicy(settings)
        xv, Pv, work = _storage(x, P)
        res = update_inplace(settings, policy, xv, Pv, y, h, H, None, R, bnd, work)
        np.testing.assert_allclose(Pv, ref.P, rtol=0, atol=1e-12 * np.abs(ref.P).max())
        np.testing.assert_allclose(xv, ref.x, rtol=0, atol=1e-12 * np.abs(ref.x).max())
        assert res.gamma == ref.gamma and res.gamma_raised == ref.gamma_raised
        assert policy.raised_count == int(ref.gamma_raised)
        assert policy.gamma == (ref.gamma if ref.gamma_raised else settings.gamma)
