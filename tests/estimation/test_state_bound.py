"""NH-infinity's bound on a chosen set of vehicles (`JointState.update(vehicles=...)`): the
vehicles whose pose is known; none bounded is the EKF with R_hat."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.filters import ekf_update, hinf_update
from cvslam_cli.estimation.state import FilterSettings
from tests.estimation.test_state import RNG, _state


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
        res = st.update(s, y, h, H, cols, R, vehicles=vehicles)
        assert res.gamma == ref.gamma and res.gamma_raised == ref.gamma_raised
        np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12)


def test_no_vehicle_bounded_is_the_ekf_with_the_scaled_noise():
    s = FilterSettings("hinf", gamma=1.5, c_v=1.2)
    st = _state()
    y, h, H, cols, R = _observation(st)
    ref = ekf_update(st.x.copy(), st.P.copy(), y, h, H, s.r_scale * R, cols=cols)
    st.update(s, y, h, H, cols, R, vehicles=[])
    np.testing.assert_allclose(st.x, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(st.P, ref.P, rtol=0, atol=1e-12)
