"""Relocalisation (`estimation/relocalisation.py`): a vehicle whose pose the map contradicts
forgets it, with what it mapped since it was last confirmed, and is found again in the map
by appearance; the pieces (a point mapped twice, the rows forgotten, the state decoupled)
and the whole, on the loop UAV with an accelerometer glitch."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.estimation.landmark_coordinates import coordinates
from cvslam_cli.estimation.localise import descriptor_pairs
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import ConstantVelocityModel, InsModel, OdometryModel
from cvslam_cli.estimation.reactivation import MAX_REACTIVATION_STD_M
from cvslam_cli.estimation.relocalisation import forget_mapped, lost_variances
from cvslam_cli.estimation.settings import RelocalisationSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.unknown_pose import pose_found_dominates
from cvslam_cli.geometry.rotations import interpolate_positions
from tests.scenarios import (
    MC_FILTER_OVERRIDES,
    accelerometer_glitch,
    blackout,
    ekf_on_simulation,
    simulate_loop_uav,
)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def test_a_point_mapped_twice_pairs_with_its_older_mapping() -> None:
    """Two map rows with nearly the same descriptor (one point mapped twice) fail the ratio
    test against each other; with their ages the match pairs with the older. A match between
    two different points stays ambiguous either way."""
    rng = np.random.default_rng(3)
    desc_map = rng.integers(0, 256, (40, 128)).astype(np.int64)
    noise = rng.integers(-6, 7, 128)
    desc_map[25] = desc_map[7] + noise  # row 25: point 7 mapped again
    between = (desc_map[10] + desc_map[11]) // 2
    obs = np.vstack([desc_map[7] + noise // 2, desc_map[3] + 2, between])
    desc_map = np.clip(desc_map, 0, 255).astype(np.uint8)
    obs = np.clip(obs, 0, 255).astype(np.uint8)
    rows, lm = descriptor_pairs(obs, desc_map, ratio=0.8, max_distance=1e9)
    assert dict(zip(rows.tolist(), lm.tolist(), strict=True)) == {1: 3}
    age = np.arange(40)[::-1].copy()  # row 25 mapped before row 7
    rows, lm = descriptor_pairs(obs, desc_map, ratio=0.8, max_distance=1e9, age=age)
    assert dict(zip(rows.tolist(), lm.tolist(), strict=True)) == {0: 25, 1: 3}
    rows, lm = descriptor_pairs(obs, desc_map, ratio=0.8, max_distance=1e9, age=np.arange(40))
    assert dict(zip(rows.tolist(), lm.tolist(), strict=True)) == {0: 7, 1: 3}


@pytest.mark.parametrize(
    ("model", "forgotten"),
    [
        (InsModel(InsNoise(2e-3, 1.7e-4, 3e-3, 2e-5), biases=True), range(9)),
        (OdometryModel(0.05, 0.01), range(3)),
        (ConstantVelocityModel(2.0, 0.5), range(9)),
    ],
)
def test_a_lost_vehicle_forgets_its_pose_and_velocity_not_its_biases(
    model: Any, forgotten: range
) -> None:
    s = RelocalisationSettings(
        position_sigma_m=20.0, velocity_sigma_m_s=5.0, attitude_sigma_rad=0.2
    )
    rows, var = lost_variances(model, s)
    assert list(rows) == list(forgotten)
    names = [model.state_names[i] for i in rows]
    for name, v in zip(names, var, strict=True):
        kind = name.split("_")[0] if "_" in name else "attitude"
        assert v == pytest.approx({"p": 400.0, "v": 25.0, "attitude": 0.04}[kind]), name


def test_forget_decouples_the_vehicle_and_keeps_the_rest_of_the_state() -> None:
    rng = np.random.default_rng(1)
    model = ConstantVelocityModel(2.0, 0.5)
    A = rng.normal(size=(12, 12))
    st = JointState([("a", model, np.zeros(12), A @ A.T + np.eye(12))], coordinates("cartesian"))
    B = rng.normal(size=(9, 9))
    st.add_landmarks(rng.normal(size=(3, 3)), B @ B.T + np.eye(9), rng.normal(size=(9, 12)) * 0.1)
    P0 = st.P.copy()
    rows, var = np.array([0, 1, 2, 8]), np.array([4.0, 4.0, 4.0, 0.25])
    st.forget("a", rows, var)
    P = st.P
    np.testing.assert_array_equal(P, P.T)
    np.testing.assert_array_equal(P[:12, 12:], 0.0)  # the vehicle independent of the map
    np.testing.assert_array_equal(P[12:, 12:], P0[12:, 12:])  # the map as it was
    np.testing.assert_array_equal(np.diag(P)[rows], var)
    kept = np.setdiff1d(np.arange(12), rows)
    np.testing.assert_array_equal(P[np.ix_(rows, kept)], 0.0)
    np.testing.assert_array_equal(P[np.ix_(kept, kept)], P0[np.ix_(kept, kept)])
    assert np.linalg.eigvalsh(P).min() > 0


def test_what_the_vehicle_alone_mapped_since_it_was_confirmed_is_forgotten() -> None:
    """Landmarks first seen after the vehicle's last confirmation (the later of its last
    agreeing check and a check interval before it last tracked the map) and observed by it
    alone leave the state and are never used again; older ones, and ones another vehicle
    saw, stay."""
    st = JointState(
        [("a", ConstantVelocityModel(2.0, 0.5), np.zeros(12), np.eye(12))],
        coordinates("cartesian"),
    )
    book = LandmarkBook(2)
    k = 6
    st.add_landmarks(np.arange(3.0 * k).reshape(k, 3), np.eye(3 * k), np.zeros((3 * k, 12)))
    desc = np.zeros((k, 128), dtype=np.uint8)
    seen = np.array([100, 100, 300, 300, 300, 300])
    for i in range(k):
        vehicle = 1 if i == 3 else 0
        book.add(desc[i : i + 1], vehicle, int(seen[i]), np.array([i]), np.array([[0.0, 0, -1]]))
    book.observe(np.array([4]), 1, 310, np.array([[0.0, 0, -1]]), np.array([10.0]))  # both
    run = SimpleNamespace(index=0, verified_ns=200, tracked_ns=250, vin=SimpleNamespace(start_ns=0))
    n = forget_mapped(st, book, run, 400, 400.0, 100)  # type: ignore[arg-type]
    assert n == 2  # landmarks 2 and 5
    assert sorted(book.slot_ids.tolist()) == [0, 1, 3, 4] and st.n_landmarks == 4
    assert book.forgotten[:k].tolist() == [False, False, True, False, False, True]
    np.testing.assert_array_equal(book.cov_nav_m2[[2, 5]], np.tile(400.0 * np.eye(3), (2, 1, 1)))
    assert not book.known(np.array([2, 5]), MAX_REACTIVATION_STD_M).any()


GLITCH_AT_S, GLITCH_S, GLITCH_M_S2 = 20.0, 1.0, 4.0


@pytest.fixture(scope="module")
def loop_sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate_loop_uav(tmp_path_factory.mktemp("loop"), 30.0, [1])[0]


def _errors(res: Any, truth: Any) -> tuple[np.ndarray, np.ndarray]:
    tr = res.tracks["uav1"]
    e = tr.p_nav_m - interpolate_positions(truth.stamps_ns, truth.p_nav_m, tr.stamps_ns)
    return (tr.stamps_ns - tr.stamps_ns[0]) * 1e-9, np.linalg.norm(e, axis=1)


def test_an_imu_glitch_is_caught_by_appearance_and_the_vehicle_found_again(loop_sim: Path):
    """The accelerometer 4 m/s^2 off for 1 s: unchecked, the filter ends 10 m off with a
    position sigma under 1 m; checked against the map by appearance, it is lost within
    seconds of the glitch, found again, and ends near its error without the glitch."""
    runs = {}
    for on in (False, True):
        cfg = load_config((), [*MC_FILTER_OVERRIDES, f"fuse.relocalisation.enabled={on}"])
        glitch = accelerometer_glitch(GLITCH_AT_S, GLITCH_S, GLITCH_M_S2)
        res, truth = ekf_on_simulation(loop_sim, cfg, edit_inputs=glitch)
        assert res.divergence is None
        runs[on] = (res, *_errors(res, truth))
    (off, _, err_off), (on, t_s, err_on) = runs[False], runs[True]
    rmse = {k: float(np.sqrt(np.mean(v[2] ** 2))) for k, v in runs.items()}
    lost = [e for e in on.events if e["event"] == "lost"]
    print(
        f"\nglitch unchecked: final {err_off[-1]:.2f} m, RMSE {rmse[False]:.2f} m; checked: "
        f"final {err_on[-1]:.2f} m, RMSE {rmse[True]:.2f} m; lost: "
        + "; ".join(e["detail"] for e in lost)
    )
    assert not any(e["event"] in ("lost", "relocalisation") for e in off.events)
    assert err_off[-1] > 8.0
    assert lost and all("map by appearance" in e["detail"] for e in lost)
    assert any(e["event"] == "relocalisation" for e in on.events)
    # lost within 2 s of the glitch (events merge frames: the timeline has every one)
    lost_s = np.array(
        [(r["stamp_ns"] - on.timeline[0]["stamp_ns"]) * 1e-9 for r in on.timeline if r["lost"]]
    )
    assert ((lost_s > GLITCH_AT_S) & (lost_s < GLITCH_AT_S + 2.0)).any(), lost_s
    assert err_on[-1] < 3.0 and rmse[True] < 0.4 * rmse[False]
    after = t_s > GLITCH_AT_S + 4.0
    assert err_on[after].max() < 3.0


def test_a_vehicle_too_uncertain_for_its_windows_is_found_by_appearance(tmp_path: Path):
    """After 45 s without images the loop UAV (seed 4) comes back 200 m off at a position
    sigma of 58 m: its windows would take look-alikes (135 m off at 8 m sigma, to the end);
    found by appearance instead (a `recognition` event), it ends near the truth."""
    sim = simulate_loop_uav(tmp_path, 60.0, [4])[0]
    cfg = load_config((), list(MC_FILTER_OVERRIDES))
    res, truth = ekf_on_simulation(sim, cfg, edit=lambda fs: blackout(fs, 5.0, 50.0))
    assert res.divergence is None
    t_s, err = _errors(res, truth)
    found = [e for e in res.events if e["event"] == "recognition"]
    print(f"\nafter a 45 s blackout: final {err[-1]:.2f} m; " + found[0]["detail"])
    assert found and "found by appearance" in found[0]["detail"]
    assert err[t_s > 52.0].max() < 1.5 and err[-1] < 0.5


def test_a_pose_found_replaces_the_filters_only_where_it_carries_all_there_is():
    """The weight P (P + C)^-1 of a pose found against the filter's pose: at least 0.99 in
    every direction of position and heading (the blackout above: the filter's variance
    thousands of times the pose found's) moves the vehicle to it; a pose found about as
    certain as the filter's in one direction (a ground robot among nearby walls) leaves the
    vehicle its own pose for the update (unknown_pose.relocalise)."""
    P = np.diag([58.0**2] * 3 + [0.01, 0.01, 0.2])
    C = np.diag([0.3**2] * 3 + [0.01, 0.01, 0.002])
    weight = np.linalg.solve(P + C, P).T
    assert pose_found_dominates(weight)
    P[5, 5] = C[5, 5]  # the heading known as well as the pose found knows it
    assert not pose_found_dominates(np.linalg.solve(P + C, P).T)
    # roll and pitch do not count: a pose found replaces position and heading only
    P = np.diag([58.0**2] * 3 + [1e-6, 1e-6, 0.2])
    assert pose_found_dominates(np.linalg.solve(P + C, P).T)
