"""The gauge basis and the observability-constrained update (estimation/gauge.py)."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.filters import FilterSettings, GammaPolicy
from cvslam_cli.estimation.gauge import constrain, constrained, gauge_correlated, vehicle_basis
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import (
    ConstantVelocityModel,
    InsModel,
    OdometryModel,
)
from cvslam_cli.estimation.state import JointState

RNG = np.random.default_rng(7)
INS = InsModel(InsNoise(2e-3, 1.7e-4, 3e-3, 2e-5), biases=True)
CV = ConstantVelocityModel(2.0, 0.5)
ODO = OdometryModel(0.05, 0.01, z_nav_m=-0.3)


def _state(model, rng):
    x = model.initial_state(
        rng.normal(0, 50, 3), rng.normal(0, 0.2, 3), rng.normal(0, 5, 3), rng.normal(0, 0.1, 3)
    )
    if model is INS:
        x[9:] = rng.normal(0, 0.01, 6)
    return x


def _input(model, rng):
    return rng.normal(0, 1, model.input_size) + (
        np.array([0, 0, -9.81, 0, 0, 0]) if model is INS else 0.0
    )


@pytest.mark.parametrize("model", [INS, CV, ODO], ids=["ins", "cv", "odometry"])
def test_the_basis_is_a_symmetry_of_each_motion_model(model):
    """Moving the state along a gauge direction before a step moves it along the same
    direction of the stepped state (f(x + e n(x)) = f(x) + e n(f(x))): F N(x) = N(f(x))."""
    down = "p_d" in model.state_names
    for _ in range(5):
        x = _state(model, RNG)
        u, dt = _input(model, RNG), 0.05
        x_new, F, _ = model.step(x, u, dt)
        np.testing.assert_allclose(
            F @ vehicle_basis(model, x, down), vehicle_basis(model, x_new, down), atol=1e-9
        )
        N = vehicle_basis(model, x, down)
        for col in range(N.shape[1]):  # the nonlinear step, not only its Jacobian
            e = 1e-6
            moved, _, _ = model.step(x + e * N[:, col], u, dt)
            np.testing.assert_allclose(
                (moved - x_new) / e, vehicle_basis(model, x_new, down)[:, col], atol=1e-5
            )


def test_constrain_removes_the_gauge_and_nothing_else():
    N = RNG.normal(size=(3, 9, 4))
    H = RNG.normal(size=(3, 4, 9))
    H_c = constrain(H, N)
    np.testing.assert_allclose(H_c @ N, 0.0, atol=1e-12)
    # rows that already see nothing of the gauge are left alone
    np.testing.assert_allclose(constrain(H_c, N), H_c, atol=1e-12)


def _gauge_information(st: JointState) -> np.ndarray:
    return st.N.T @ np.linalg.solve(st.P, st.N)


def _joint_state(vehicles: int = 1):
    """`vehicles` INS vehicles ("uav", "uav2", ...) and 4 Cartesian landmarks added by the
    chain rule from the first one's pose."""
    st = JointState(
        [
            (name, INS, _state(INS, RNG), np.diag(RNG.uniform(1e-4, 1e-3, INS.n)))
            for name in ["uav", *(f"uav{i + 2}" for i in range(vehicles - 1))]
        ],
        gauge=True,
    )
    vb = st.vehicles["uav"]
    k = 4
    G = RNG.normal(size=(3 * k, INS.n))
    N_v = st.N[vb.index]
    # a landmark moves with the gauge as the chain rule says: choose G so that G N_v equals
    # the symmetry's rows of a point at m (translation, turn about down)
    m = RNG.normal(0, 30, (k, 3))
    N_m = np.zeros((3 * k, 4))
    for j in range(k):
        N_m[3 * j : 3 * j + 3, :3] = np.eye(3)
        N_m[3 * j : 3 * j + 3, 3] = [-m[j, 1], m[j, 0], 0.0]
    G += (N_m - G @ N_v) @ np.linalg.pinv(N_v)
    P_mx = G @ st.P[vb.index, :]
    P_mm = P_mx[:, vb.index] @ G.T + np.eye(3 * k) * 0.04
    st.add_landmarks(m, P_mm, P_mx, N_p=st.gauge_rows(G, vb.index))
    return st


def _constrained_steps(st: JointState, steps: int) -> None:
    """`steps` propagations of "uav", each followed by a random constrained EKF update over
    every column of the state."""
    settings, gamma = FilterSettings("ekf"), GammaPolicy(FilterSettings("ekf"))
    cols = np.arange(st.n)
    for _ in range(steps):
        x_new, F, Q = INS.step(st.vehicle_x("uav"), _input(INS, RNG), 0.05)
        st.predict("uav", x_new, F, Q)
        H = constrain(RNG.normal(size=(6, st.n)), st.N)
        st.update(settings, gamma, RNG.normal(size=6), np.zeros(6), H, cols, np.eye(6) * 0.1)


def test_constrained_updates_add_no_information_about_the_gauge():
    """The property the module exists for: Nᵀ P⁻¹ N is what the prior gave, after any
    number of constrained updates and propagations; unconstrained rows (an H evaluated
    away from the estimate) add information along it."""
    st = _joint_state()
    before = _gauge_information(st)
    _constrained_steps(st, 10)
    after = _gauge_information(st)
    # process noise only lowers it
    assert np.all(np.diag(after) <= np.diag(before) * (1 + 1e-9))
    settings, gamma = FilterSettings("ekf"), GammaPolicy(FilterSettings("ekf"))
    H = RNG.normal(size=(6, st.n))
    st.update(
        settings, gamma, RNG.normal(size=6), np.zeros(6), H, np.arange(st.n), np.eye(6) * 1e-4
    )
    assert np.all(np.diag(_gauge_information(st)) > 1.01 * np.diag(after))


@pytest.mark.parametrize("vehicles", [1, 2])
def test_a_point_put_back_adds_no_information_about_the_gauge(vehicles):
    """Whatever the updates made of the correlations: the gauge error the vehicles' blocks
    read is the one the point shares (gauge.gauge_correlated's L N = I)."""
    st = _joint_state(vehicles)
    _constrained_steps(st, 5)
    before = _gauge_information(st)
    k = 2
    m = RNG.normal(0, 30, (k, 3))
    N_m = np.zeros((k, 3, 4))
    N_m[:, :, :3] = np.eye(3)
    N_m[:, 0, 3], N_m[:, 1, 3] = -m[:, 1], m[:, 0]
    C = np.broadcast_to(np.eye(3) * 25.0, (k, 3, 3))
    P_mm, P_mx = gauge_correlated(st.P, st.N, N_m, C, st.n_vehicle_states)
    # its marginals are the ones asked for
    for j in range(k):
        np.testing.assert_allclose(P_mm[3 * j : 3 * j + 3, 3 * j : 3 * j + 3], C[j], atol=1e-9)
    st.add_landmarks(m, P_mm, P_mx, N_p=N_m.reshape(3 * k, 4))
    np.testing.assert_allclose(_gauge_information(st), before, atol=1e-6 * np.abs(before).max())
    # inserted independently (the filter without a gauge), the same points would add it
    st2 = _joint_state()
    before2 = _gauge_information(st2)
    P_ind = np.kron(np.eye(k), np.eye(3) * 25.0)
    st2.add_landmarks(m, P_ind, np.zeros((3 * k, st2.n)), N_p=N_m.reshape(3 * k, 4))
    # (each point tells 1 / 25 m^-2 of the team's north position)
    assert _gauge_information(st2)[0, 0] - before2[0, 0] > 0.9 * k / 25.0


def test_the_down_translation_leaves_the_gauge_with_a_ground_robot():
    st = JointState(
        [
            ("uav", INS, _state(INS, RNG), np.eye(INS.n) * 0.01),
            ("robot", ODO, _state(ODO, RNG), np.eye(ODO.n) * 0.01),
        ],
        gauge=True,
    )
    assert st.N.shape == (INS.n + ODO.n, 3)
    assert JointState([("uav", INS, _state(INS, RNG), np.eye(INS.n))], gauge=True).N.shape[1] == 4
    assert JointState([("uav", INS, _state(INS, RNG), np.eye(INS.n))]).N is None


def test_auto_constrains_a_team_whose_every_vehicle_measures_its_motion():
    assert constrained("auto", ["ins", "ins"]) == (
        True, "auto: every vehicle has an IMU or wheel odometry"
    )  # fmt: skip
    assert constrained("auto", ["ins", "odometry"])[0]  # a mixed team
    assert constrained("auto", ["odometry", "odometry"])[0]  # ground robots
    assert not constrained("auto", ["ins", "constant_velocity"])[0]
    assert not constrained("auto", ["constant_velocity"])[0]
    assert not constrained("auto", [])[0]
    assert constrained(True, ["odometry"])[0] and not constrained(False, ["ins"])[0]
    with pytest.raises(ValueError, match="observability_constrained"):
        constrained("false", ["ins"])  # type: ignore[arg-type]
