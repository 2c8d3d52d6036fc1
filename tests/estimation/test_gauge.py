"""The gauge basis and the observability-constrained update (estimation/gauge.py)."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.estimation.filters import FilterSettings, GammaPolicy
from cvslam_cli.estimation.gauge import (
    constrain,
    constrained,
    gauge_correlated,
    team_pivot,
    vehicle_basis,
)
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import (
    ConstantVelocityModel,
    InsModel,
    OdometryModel,
)
from cvslam_cli.estimation.state import JointState
from tests.scenarios import ekf_on_simulation, simulate_loop_uav

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


@pytest.mark.parametrize("model", [INS, ODO], ids=["ins", "odometry"])
def test_a_turn_about_another_pivot_spans_the_same_directions(model):
    """The turn about any pivot is the turn about the origin plus a translation: N's
    columns change, the directions they span do not."""
    down = "p_d" in model.state_names
    x = _state(model, RNG)
    N0 = vehicle_basis(model, x, down)
    pivot = RNG.normal(0, 1e3, 2)
    N1 = vehicle_basis(model, x, down, pivot)
    coef, *_ = np.linalg.lstsq(N0, N1, rcond=None)
    np.testing.assert_allclose(N0 @ coef, N1, atol=1e-9)
    assert not np.allclose(N0, N1)
    blocks = [(INS, _state(INS, RNG)), (ODO, _state(ODO, RNG)), (CV, _state(CV, RNG))]
    starts = [[x0[m.state_names.index("p_n")], x0[m.state_names.index("p_e")]] for m, x0 in blocks]
    np.testing.assert_allclose(team_pivot(blocks), np.mean(starts, axis=0))


def _moved(v, shift_ne_m: np.ndarray):
    """Vehicle input v started shift_ne_m (north, east) away, the rest of it as it was."""
    p, euler = v.model.pose(v.x0)
    return dataclasses.replace(v, x0=v.model.with_pose(v.x0, p + np.append(shift_ne_m, 0.0), euler))


def test_no_estimate_depends_on_where_the_nav_frame_s_origin_lies(tmp_path: Path) -> None:
    """A UAV where a UTM-like frame puts it (4500 km north, 500 km east of the origin) is
    estimated as the same UAV at the origin, moved, covariance and all: the gauge's turn is
    about the team's start (`team_pivot`). About the origin this run ends 0.43 m elsewhere
    (with `constrain`'s orthonormal basis; 0.11 m at only 10 km before either change; the
    60 s benchmark UAV at 10 km 0.23 m, its final position sigma 0.55 -> 0.45 m)."""
    sim = simulate_loop_uav(tmp_path, 12.0, [0])[0]
    cfg = load_config((), ["fuse.observability_constrained=true"])
    shift_ne_m = np.array([4.5e6, 5e5])  # where a UTM frame puts it

    here, _ = ekf_on_simulation(sim, cfg)
    far, _ = ekf_on_simulation(
        sim, cfg, edit_inputs=lambda inputs: [_moved(v, shift_ne_m) for v in inputs]
    )
    a, b = here.tracks["uav1"], far.tracks["uav1"]
    assert len(a.p_nav_m) == len(b.p_nav_m) > 50
    np.testing.assert_allclose(b.p_nav_m[:, :2] - shift_ne_m, a.p_nav_m[:, :2], rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.p_nav_m[:, 2], a.p_nav_m[:, 2], rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.pose_cov, a.pose_cov, rtol=1e-6, atol=1e-12)


def test_a_vehicle_that_shares_nothing_changes_nothing(tmp_path: Path) -> None:
    """The loop UAV in one filter with its twin (the same logs) flown 10 km away, where
    neither ever sees a landmark of the other: each is estimated as the UAV alone (moved),
    covariance and all. What couples two vehicles in one filter is only what they observe
    in common; the gauge is the team's, but a vehicle's updates leave another group's
    estimate alone (`gauge_correlated`'s groups). The team's pivot lies 5.6 km from each
    UAV here: with (N^T N)^+ in `constrain` in place of an orthonormal basis they part by
    0.8 mm. The pixel noise is given (measured, it pools both vehicles' frames) and the
    landmark bound never binds."""
    sim = simulate_loop_uav(tmp_path, 12.0, [0])[0]
    cfg = load_config(
        (),
        [
            "fuse.observability_constrained=true",
            "fuse.association.pixel_sigma_px=0.5",
            "fuse.map.max_landmarks=2000",
            "fuse.map.landmarks_per_added_vehicle=2000",
            "fuse.map.max_landmarks_total=4000",
        ],
    )
    shift_ne_m = np.array([1e4, -5e3])

    def with_twin(inputs: list) -> list:
        (v,) = inputs
        return [v, dataclasses.replace(_moved(v, shift_ne_m), name="twin")]

    alone, _ = ekf_on_simulation(sim, cfg)
    team, _ = ekf_on_simulation(sim, cfg, edit_inputs=with_twin)
    a = alone.tracks["uav1"]
    assert len(a.p_nav_m) > 50 and len(alone.landmarks.p_nav_m) > 100
    assert not any(";" in o for o in team.landmarks.observers)  # none seen by both
    for name, shift in (("uav1", np.zeros(2)), ("twin", shift_ne_m)):
        b = team.tracks[name]
        np.testing.assert_allclose(b.p_nav_m[:, :2] - shift, a.p_nav_m[:, :2], rtol=0, atol=1e-6)
        np.testing.assert_allclose(b.p_nav_m[:, 2], a.p_nav_m[:, 2], rtol=0, atol=1e-6)
        np.testing.assert_allclose(b.pose_cov, a.pose_cov, rtol=1e-6, atol=1e-12)


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


def _points(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """k points m (k, 3), their gauge rows N_m (k, 3, 4) and marginals C (k, 3, 3)."""
    m = RNG.normal(0, 30, (k, 3))
    N_m = np.zeros((k, 3, 4))
    N_m[:, :, :3] = np.eye(3)
    N_m[:, 0, 3], N_m[:, 1, 3] = -m[:, 1], m[:, 0]
    return m, N_m, np.broadcast_to(np.eye(3) * 25.0, (k, 3, 3))


@pytest.mark.parametrize(
    "vehicles, observers",
    [(1, [0b1, 0b1]), (2, [0b11, 0b11]), (2, [0b1, 0b1]), (2, [0b1, 0b10])],
    ids=["one", "both-read-both", "both-read-first", "one-point-each"],
)
def test_a_point_put_back_adds_no_information_about_the_gauge(vehicles, observers):
    """Whatever the updates made of the correlations and whichever vehicles' blocks each
    point's gauge error is read from (its observers, a group per set of them): it is one the
    point shares (gauge.gauge_correlated's L N = I)."""
    st = _joint_state(vehicles)
    _constrained_steps(st, 5)
    before = _gauge_information(st)
    k = 2
    m, N_m, C = _points(k)
    masks = np.array(observers)
    groups = [(np.flatnonzero(masks == b), st.vehicle_rows(int(b))) for b in np.unique(masks)]
    P_mm, P_mx = gauge_correlated(st.P, st.N, N_m, C, groups)
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


def test_a_point_put_back_is_tied_only_to_the_vehicles_that_saw_it():
    """Two vehicles that never shared a landmark have a gauge each and no correlation: a
    point the first one observed, put back, is correlated with it alone, and its later
    observation by the first one leaves the second one's estimate as it was. Read from every
    vehicle's blocks, the point is tied to the second one too, and the same observation
    moves it."""
    st = _joint_state(2)  # the landmarks come from "uav"'s pose; "uav2" shares nothing
    settings, gamma = FilterSettings("ekf"), GammaPolicy(FilterSettings("ekf"))
    other = st.vehicles["uav2"].index
    own = np.setdiff1d(np.arange(st.n), other)
    for _ in range(5):  # "uav" flies and observes its own landmarks
        x_new, F, Q = INS.step(st.vehicle_x("uav"), _input(INS, RNG), 0.05)
        st.predict("uav", x_new, F, Q)
        H = constrain(RNG.normal(size=(6, len(own))), st.N[own])
        st.update(settings, gamma, RNG.normal(size=6), np.zeros(6), H, own, np.eye(6) * 0.1)
    assert np.all(st.P[np.ix_(other, own)] == 0.0)
    m, N_m, C = _points(1)
    z = RNG.normal(size=3)

    def put_back_and_observe(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = copy.deepcopy(st)
        P_mm, P_mx = gauge_correlated(s.P, s.N, N_m, C, [(np.arange(1), rows)])
        slots = s.add_landmarks(m, P_mm, P_mx, N_p=N_m.reshape(3, 4))
        seen = np.concatenate([s.vehicles["uav"].index, s.landmark_columns(slots).ravel()])
        H = constrain(np.ones((3, len(seen))), s.N[seen])
        s.update(settings, gamma, z, np.zeros(3), H, seen, np.eye(3) * 0.1)
        return P_mx[:, other], s.x[other], s.P[np.ix_(other, other)]

    P_mo, x_o, P_oo = put_back_and_observe(st.vehicle_rows(0b1))
    assert np.all(P_mo == 0.0)
    np.testing.assert_array_equal(x_o, st.x[other])
    np.testing.assert_array_equal(P_oo, st.P[np.ix_(other, other)])
    P_mo, x_o, P_oo = put_back_and_observe(np.arange(st.n_vehicle_states))  # every vehicle
    assert np.abs(P_mo).max() > 1e-6
    assert np.abs(x_o - st.x[other]).max() > 1e-6
    assert not np.array_equal(P_oo, st.P[np.ix_(other, other)])


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
