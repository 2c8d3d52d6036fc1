"""Corrections too large for one linearisation (`estimation/linearisation.py`): when a
vehicle is too uncertain for the frame it sees, or a landmark for its bearing, and the
iterated update that brings a vehicle back after a camera blackout (BENCHMARKS.md "Fuse:
large corrections") and a far landmark seen from the side (BENCHMARKS.md "Fuse: a far
landmark seen from the side")."""

from __future__ import annotations

import functools
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.estimation.filters import FilterSettings
from cvslam_cli.estimation.linearisation import bearings_too_uncertain, too_uncertain
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import InsModel
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.update import VisualUpdater
from cvslam_cli.estimation.vehicle import VehiclePose
from cvslam_cli.geometry.rotations import interpolate_poses
from cvslam_cli.sim.scenario import StereoRigSpec
from cvslam_cli.sim.vehicles import build_rig
from tests.scenarios import (
    MC_FILTER_OVERRIDES,
    blackout,
    ekf_on_simulation,
    simulate_loop_uav,
)

INS = InsModel(InsNoise(2e-3, 1.7e-4), biases=False)


def test_too_uncertain_compares_the_position_sigma_with_the_frames_depth() -> None:
    cov = np.diag([4.0, 1.0, 1.0])  # 2 m along x, the least known direction
    points = np.array([[0.0, 0.0, 30.0], [1.0, 1.0, 40.0], [0.0, 0.0, 50.0], [0, 0, np.nan]])
    assert too_uncertain(cov, points, 0.049)  # 2 m > 0.049 x 40 m (the median depth)
    assert not too_uncertain(cov, points, 0.051)
    assert not too_uncertain(cov, points, 0.0)  # 0: never
    assert not too_uncertain(cov, points[:0], 0.01)  # no point, no update to linearise
    assert not too_uncertain(cov, -points[:3], 0.01)  # none in front of the camera


def test_bearings_too_uncertain_compares_a_predictions_spread_with_the_limit() -> None:
    R = np.eye(2) * 0.25  # 0.5 px of pixel noise: not the prediction's uncertainty
    S = np.array([np.diag([0.25 + 9.0, 0.25 + 1.0]), np.diag([0.25 + 400.0, 0.25])])
    # the second landmark's prediction spreads 20 px along u: 0.04 rad at fx 500
    assert bearings_too_uncertain(S, R, 500.0, 0.039)
    assert not bearings_too_uncertain(S, R, 500.0, 0.041)
    assert not bearings_too_uncertain(S[:1], R, 500.0, 0.0061)  # 3 px: 0.006 rad
    assert bearings_too_uncertain(S[:1], R, 500.0, 0.0059)
    assert not bearings_too_uncertain(S, R, 500.0, 0.0)  # 0: never
    assert not bearings_too_uncertain(S[:0], R, 500.0, 0.01)  # nothing observed
    # each observation's own noise (k, 2, 2): all of the second's spread is its noise
    R_each = np.array([R, np.diag([400.25, 0.25])])
    assert not bearings_too_uncertain(S, R_each, 500.0, 0.0061)


def _seen_from_the_side(off_m: float, iterations: int) -> tuple[float, bool]:
    """A landmark mapped far along another vehicle's ray (7 m of standard deviation along
    it), its estimate off_m along that ray, seen once by a down-looking UAV 20 m above it
    whose ray crosses the first at 45 degrees: the landmark's position NEES after the
    update with `iterations` linearisations, and whether `bearings_too_uncertain` (0.05
    rad) asks for more than one."""
    obs = StereoObservationModel.from_rig(build_rig("t", StereoRigSpec(rectified=True)))
    vin = SimpleNamespace(name="uav", obs=obs, model=INS, right_cx_px=0.0)
    p, euler = np.array([0.0, 0.0, -20.0]), np.zeros(3)
    m_true = np.array([[3.0, 2.0, 0.0]])
    ray = np.array([1.0, 0.0, -1.0]) / np.sqrt(2.0)
    st = JointState([("uav", INS, np.concatenate([p, np.zeros(3), euler]), np.eye(9) * 1e-6)])
    P_m = 7.0**2 * np.outer(ray, ray) + 0.03**2 * np.eye(3)
    slots = st.add_landmarks(m_true + off_m * ray, P_m, np.zeros((3, st.n)))
    z = obs.predict(p, euler, m_true)[0] + np.random.default_rng(1).normal(0, 0.5, (1, 4))
    up = VisualUpdater(st, FilterSettings(kind="ekf"), 0.5)
    pred, _ = up.predict(VehiclePose.of(st, vin), slots)
    flagged = bearings_too_uncertain(
        pred.S[:, :2, :2], up.R_pixel_hat[:2, :2], obs.K[0][0, 0], 0.05
    )
    up.iterated_update(vin, pred, np.arange(1), z, ["uav"], iterations=iterations)
    e = st.landmarks(slots)[0] - m_true[0]
    return float(e @ np.linalg.solve(st.landmark_covariances(slots)[0], e)), flagged


def test_a_far_landmark_seen_from_the_side_needs_more_than_one_linearisation() -> None:
    """The cooperative yard's failure (BENCHMARKS.md "Fuse: a far landmark seen from the
    side"): 4 m off along its mapper's ray, one linearised update leaves the landmark half
    a metre off under centimetres (NEES in the hundreds); relinearised at its own estimate
    it lands within its covariance. The criterion flags it."""
    nees_once, flagged = _seen_from_the_side(4.0, 1)
    nees_iterated, _ = _seen_from_the_side(4.0, 5)
    assert flagged
    assert nees_once > 100.0 > 11.34 > nees_iterated  # chi2(3) at 0.99
    assert _seen_from_the_side(2.0, 1)[0] > 11.34  # already at 2 m


BLACKOUT_S = (1.0, 19.0)  # the camera sees nothing; the UAV is back over its start at 19 s
DURATION_S = 28.0


@pytest.fixture(scope="module")
def blackout_sims(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """The Monte Carlo UAV on a 60 m diamond (`tests/scenarios.py`, `simulate_loop_uav`),
    seeds 0 and 1."""
    return simulate_loop_uav(tmp_path_factory.mktemp("blackout"), DURATION_S, (0, 1))


def _after_return(sims: list[Path], *overrides: str) -> tuple[float, float, int]:
    """Over the runs with the blackout: position RMSE (m) and mean position NEES of the
    frames after the return (from 1 s after the blackout), and the updates iterated."""
    cfg = load_config((), [*MC_FILTER_OVERRIDES, *overrides])
    err2, nees, iterated = [], [], 0
    for d in sims:
        res, gt = ekf_on_simulation(d, cfg, functools.partial(blackout, start_s=BLACKOUT_S[0],
                                                              end_s=BLACKOUT_S[1]))  # fmt: skip
        assert res.divergence is None
        tr = res.tracks["uav1"]
        p_t, _, _ = interpolate_poses(gt.stamps_ns, gt.p_nav_m, gt.q_nav_body_xyzw, tr.stamps_ns)
        after = (tr.stamps_ns - tr.stamps_ns[0]) * 1e-9 >= BLACKOUT_S[1] + 1.0
        e = (tr.p_nav_m - p_t)[after]
        err2.append(np.sum(e**2, axis=1))
        P = tr.pose_cov[after, :3, :3]
        nees.append(np.einsum("fi,fi->f", e, np.linalg.solve(P, e[..., None])[..., 0]))
        iterated += sum(r["linearisations"] > 1 for r in res.timeline)
    return (
        float(np.sqrt(np.mean(np.concatenate(err2)))),
        float(np.mean(np.concatenate(nees))),
        iterated,
    )


@pytest.fixture(scope="module")
def after_blackout(blackout_sims: list[Path]) -> dict[str, tuple[float, float, int]]:
    """`_after_return` with one linearisation per frame ("once") and with the default,
    which iterates the updates of a vehicle too uncertain for one ("iterated")."""
    return {
        "once": _after_return(blackout_sims, "fuse.association.iterate_sigma_ratio=0"),
        "iterated": _after_return(blackout_sims),
    }


def test_the_iterated_update_brings_a_vehicle_back_after_a_blackout(after_blackout):
    """18 s without images: the UAV comes back over its start with metres of error. One
    linearised update leaves it metres off and overconfident; iterated, the error after the
    return is a fraction of it, and so is the NEES."""
    once, nees_once, n_once = after_blackout["once"]
    iterated, nees_iterated, n_iterated = after_blackout["iterated"]
    print(
        f"\nafter an 18 s blackout: one linearisation RMSE {once:.2f} m, NEES {nees_once:.1f}; "
        f"iterated ({n_iterated} updates) RMSE {iterated:.2f} m, NEES {nees_iterated:.1f}"
    )
    assert n_once == 0 and 1 <= n_iterated <= 10  # only the frames that need it
    assert iterated < 0.4 * once
    assert nees_iterated < 0.2 * nees_once


def test_after_the_blackout_the_covariance_holds_the_error(after_blackout):
    """The position NEES after the return inside 2x its expected 3 (seeds 0-1: 4.4; seeds
    0-7 6.4, 6.2 before the one-correction test took each landmark given the vehicle and 7.2
    while each IMU sample was held until the next: BENCHMARKS.md, "Fuse: the IMU between its
    samples", "Fuse: the one-correction test, given the vehicle")."""
    assert after_blackout["iterated"][1] < 6.0
