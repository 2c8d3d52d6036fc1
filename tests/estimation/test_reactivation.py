"""Re-activation of evicted landmarks (`estimation/reactivation.py`): re-inserted as the
archived nav-frame Gaussian with an inflated covariance and no correlation with the state,
in either landmark coordinates; found again in a frame by predicted pixel and descriptor."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.new_landmarks import _anchored, _cartesian
from cvslam_cli.estimation.reactivation import MAX_REACTIVATION_STD_M, Reactivation
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.vehicle import VehiclePose
from cvslam_cli.geometry.rotations import interpolate_poses
from tests.estimation.test_landmark_coordinates import _points, _state, _Vehicle
from tests.scenarios import MC_FILTER_OVERRIDES, ekf_on_simulation, simulate_loop_uav


def _mapped(name: str, k: int = 6, n_vehicles: int = 1):
    """A state with k landmarks of one vehicle (vehicle 0 of the book's `n_vehicles`),
    booked; landmarks 1 and 4 evicted."""
    rng = np.random.default_rng(5)
    st = _state(name, rng)
    pose = VehiclePose.of(st, _Vehicle())
    p_cam, cov = _points(k, rng)
    if st.coords.anchored:
        slots, _ = _anchored(st, _Vehicle(), pose, p_cam, cov, None)
    else:
        slots = _cartesian(st, _Vehicle(), pose, p_cam, cov)
    book = LandmarkBook(n_vehicles)
    desc = rng.integers(0, 256, (k, 128)).astype(np.uint8)
    book.add(desc, 0, 1000, np.arange(k), np.tile([0.0, 0.0, -1.0], (k, 1)))
    evict = np.array([1, 4])
    book.evict(evict, st.landmarks(evict), st.landmark_covariances(evict), 2000)
    book.keep_slots(st.remove_landmarks(evict))
    return st, book, slots


@pytest.mark.parametrize("name", ["cartesian", "inverse_depth"])
def test_reinserted_landmark_is_the_inflated_archived_gaussian_uncorrelated(name: str) -> None:
    st, book, _ = _mapped(name)
    settings = SlamSettings(reactivation_inflation=4.0)
    r = Reactivation(st, book, settings, np.eye(4))
    ids = np.array([4, 1])
    slots = r.reinsert(SimpleNamespace(vin=_Vehicle()), ids)
    assert list(book.slot_ids[slots]) == [4, 1] and list(book.reactivations[:6]) == [
        0,
        1,
        0,
        0,
        1,
        0,
    ]
    np.testing.assert_allclose(st.landmarks(slots), book.p_nav_m[ids], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(
        st.landmark_covariances(slots), 4.0 * book.cov_nav_m2[ids], rtol=1e-9, atol=1e-9
    )
    # no correlation with the vehicle, the other landmarks, or each other (nav frame)
    cols = st.landmark_columns(slots)
    _, M = st.landmarks_nav(slots)
    others = np.setdiff1d(np.arange(st.n), cols.ravel())
    if st.coords.anchored:  # the new anchor is a clone of the vehicle: correlated with it
        others = np.setdiff1d(others, cols[:, :6].ravel())
    cross = M @ st.P[cols[:, :, None], others[None, None, :]]
    assert np.abs(cross).max() < 1e-9 * np.abs(st.P).max()
    cols_all = st.landmark_columns(slots).reshape(-1)
    J = np.zeros((6, len(cols_all)))
    J[:3, : cols.shape[1]], J[3:, cols.shape[1] :] = M[0], M[1]
    joint = J @ st.P[np.ix_(cols_all, cols_all)] @ J.T
    np.testing.assert_allclose(joint[:3, 3:], 0.0, atol=1e-9)
    # positive semi-definite (a fresh anchor clone duplicates the vehicle's pose exactly)
    assert np.linalg.eigvalsh(st.P)[0] > -1e-9 * np.abs(st.P).max()


@pytest.mark.parametrize("precise", [True, False])
def test_found_again_by_predicted_pixel_and_descriptor_not_when_absent_too_briefly(
    precise: bool,
) -> None:
    st, book, _ = _mapped("inverse_depth")
    # the archived landmarks known to 0.5 m, or one of them only to 20 m (not brought back)
    book.cov_nav_m2[[1, 4]] = np.eye(3) * np.array(
        [[[0.5**2]], [[(0.5 if precise else 20.0) ** 2]]]
    )
    vin = _Vehicle()
    pose = VehiclePose.of(st, vin)
    ids = np.array([1, 4])
    z, _, _ = vin.obs.predict(pose.p_nav_m, pose.euler_rad, book.p_nav_m[ids])
    rng = np.random.default_rng(0)
    # the frame: the two evicted landmarks' pixels (slightly off) with their descriptors,
    # and a distractor far away
    frame_z = np.concatenate([z + rng.normal(scale=0.3, size=z.shape), [[5.0, 5.0, 1.0, 5.0]]])
    frame_desc = np.concatenate([book.desc[ids], rng.integers(0, 256, (1, 128)).astype(np.uint8)])
    rig = SimpleNamespace(size_px=np.array([[640, 480], [640, 480]]))
    features = SimpleNamespace(rig=rig)
    run = SimpleNamespace(
        index=0,
        vin=SimpleNamespace(
            obs=vin.obs, model=vin.model, name=vin.name, features=features, right_cx_px=0.0
        ),
    )
    frame = SimpleNamespace(z=frame_z, desc=frame_desc, stamp_ns=2000 + 6_000_000_000)
    s = SlamSettings(reactivation_min_landmarks=2, reactivation_min_absence_ns=5_000_000_000)
    found = Reactivation(st, book, s, np.eye(4) * 0.25).find(run, frame, np.ones(3, dtype=bool))
    if not precise:  # fewer than the minimum known well enough
        assert MAX_REACTIVATION_STD_M < 20.0 and len(found.ids) == 0
        return
    assert sorted(found.ids) == [1, 4] and sorted(found.match_rows) == [0, 1]
    assert np.all(found.absent_ns == 6_000_000_000 + 1000)
    # nobody saw them for less than the minimum absence: left alone
    early = SimpleNamespace(z=frame_z, desc=frame_desc, stamp_ns=3000)
    assert (
        len(Reactivation(st, book, s, np.eye(4) * 0.25).find(run, early, np.ones(3, bool)).ids) == 0
    )
    # fewer consistent matches than the minimum: no re-activation
    strict = SlamSettings(reactivation_min_landmarks=3, reactivation_min_absence_ns=5_000_000_000)
    assert (
        len(Reactivation(st, book, strict, np.eye(4) * 0.25).find(run, frame, np.ones(3, bool)).ids)
        == 0
    )


def test_another_vehicles_landmark_is_found_again_with_the_stricter_descriptor_ratio() -> None:
    """Each evicted landmark has two candidates at its predicted pixel whose descriptor
    distances are in a ratio of 0.75: the vehicle that mapped them finds them again (ratio
    0.8); another vehicle, which never observed them, does not at its ratio of 0.7 (as in the
    frame's own association) and does at 0.8."""
    st, book, _ = _mapped("inverse_depth", n_vehicles=2)
    book.cov_nav_m2[[1, 4]] = np.eye(3) * 0.5**2
    vin = _Vehicle()
    pose = VehiclePose.of(st, vin)
    ids = np.array([1, 4])
    z, _, _ = vin.obs.predict(pose.p_nav_m, pose.euler_rad, book.p_nav_m[ids])
    frame_z = np.concatenate([z + 0.2, z - 0.2])
    desc = book.desc[ids].astype(np.int64)
    near, far = desc.copy(), desc.copy()
    near[:, :16] = np.where(desc[:, :16] > 127, desc[:, :16] - 30, desc[:, :16] + 30)
    far[:, :16] = np.where(desc[:, :16] > 127, desc[:, :16] - 40, desc[:, :16] + 40)
    frame_desc = np.concatenate([near, far]).astype(np.uint8)  # distances 120 and 160
    frame = SimpleNamespace(z=frame_z, desc=frame_desc, stamp_ns=2000 + 6_000_000_000)
    rig = SimpleNamespace(size_px=np.array([[640, 480], [640, 480]]))
    features = SimpleNamespace(rig=rig)
    v = SimpleNamespace(
        obs=vin.obs, model=vin.model, name=vin.name, features=features, right_cx_px=0.0
    )
    free = np.ones(4, dtype=bool)

    def found(index: int, other_ratio: float) -> list[int]:
        s = SlamSettings(
            reactivation_min_landmarks=2, reactivation_min_absence_ns=5_000_000_000,
            other_vehicle_descriptor_ratio=other_ratio,
        )  # fmt: skip
        run = SimpleNamespace(index=index, vin=v)
        r = Reactivation(st, book, s, np.eye(4) * 0.25).find(run, frame, free)
        return sorted(r.ids)

    assert found(0, 0.7) == [1, 4]
    assert found(1, 0.7) == []
    assert found(1, 0.8) == [1, 4]


# 8 runs: a NEES averaged over 2 moves by a third from one pair of seeds to the next (seeds
# 0-1 at the default anchor of each frame: 2.63 with re-activation, 2.18 without; seeds 0-7:
# 2.88 and 2.96)
LOOP_SEEDS = range(8)
LOOP_DURATION_S = 20.0
# 60 landmarks in the state, 30 updated a frame (a UAV team's default of 60 a frame would update
# the whole state every frame)
SMALL_BOUND = ("fuse.map.max_landmarks=60", "fuse.map.max_updates_per_frame=30")
SHORT_ABSENCE = "fuse.map.reactivation_min_absence_s=5"  # the lap takes 17 s


@pytest.fixture(scope="module")
def loop_sims(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """The Monte Carlo UAV on a 60 m diamond (`tests/scenarios.py`, `simulate_loop_uav`): the
    ground of its start out of view half of each 17 s lap."""
    return simulate_loop_uav(tmp_path_factory.mktemp("loop"), LOOP_DURATION_S, LOOP_SEEDS)


def _loop_runs(sims: list[Path], *overrides: str) -> tuple[np.ndarray, float, int]:
    """Mean position NEES per frame over the runs (EKF), the RMSE (m) and the landmarks
    re-activated."""
    cfg = load_config((), [*MC_FILTER_OVERRIDES, *overrides])
    nees, err, reactivated = [], [], 0
    for d in sims:
        res, gt = ekf_on_simulation(d, cfg)
        assert res.divergence is None
        # no fault: the place-recognition checks never find the map contradicting the filter
        assert not any(e["event"] == "lost" for e in res.events)
        tr = res.tracks["uav1"]
        p_t, _, _ = interpolate_poses(gt.stamps_ns, gt.p_nav_m, gt.q_nav_body_xyzw, tr.stamps_ns)
        e = tr.p_nav_m - p_t
        P = tr.pose_cov[:, :3, :3]
        nees.append(np.einsum("fi,fi->f", e, np.linalg.solve(P, e[..., None])[..., 0]))
        err.append(np.sum(e**2, axis=1))
        reactivated += sum(r["reactivated"] for r in res.timeline)
    frames = min(len(n) for n in nees)
    mean_nees = np.mean([n[:frames] for n in nees], axis=0)[1:]
    return mean_nees, float(np.sqrt(np.mean(np.concatenate(err)))), reactivated


def test_reactivation_closes_the_loop_without_making_the_filter_overconfident(loop_sims):
    """With 60 landmarks in the state the start's ground is evicted before the UAV is back:
    re-activated, it lowers the error, and the position NEES stays near its expected 3 and
    not above the filter's without re-activation (BENCHMARKS.md, "Fuse: re-activation")."""
    off, rmse_off, n_off = _loop_runs(loop_sims, *SMALL_BOUND, "fuse.map.reactivation=false")
    on, rmse_on, n_on = _loop_runs(loop_sims, *SMALL_BOUND, SHORT_ABSENCE)
    print(
        f"\nre-activation off: NEES {off.mean():.2f}, RMSE {rmse_off:.3f} m; on: NEES "
        f"{on.mean():.2f}, RMSE {rmse_on:.3f} m, {n_on} landmarks re-activated"
    )
    assert n_off == 0 and n_on > 50
    assert rmse_on < rmse_off
    assert 1.5 < on.mean() < 4.5 and on.mean() <= 1.1 * off.mean()
    assert on[len(on) // 2 :].mean() < 4.5  # after the re-activations too
