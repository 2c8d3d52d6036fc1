"""Multi-session mapping (`estimation/prior_map.py`, `cvslam fuse --prior-map`): a map saved
by one run is read back as the next run's prior; a vehicle with an unknown initial pose is
localised in it and maps on, the outputs telling prior from new landmarks; a map of another
world never localises it; bad prior maps are one clear error line."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from cvslam_cli.errors import CvslamError
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.prior_map import PriorMap
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.geometry.rotations import interpolate_positions
from cvslam_cli.io.fuse_files import read_map_csv, write_map_csv
from cvslam_cli.io.map_file import load_map, load_prior_map, save_map
from cvslam_cli.io.npz import save_npz
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.records.landmark_archive import NEVER_NS, LandmarkArchive
from cvslam_cli.sim.scenario import load_scenario
from cvslam_cli.sim.stage import run as simulate
from tests.scenarios import small_uav_scenario

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

# uav2_paper's camera (the small scenario's, 188 x 120 at fx 112.5, maps to metres only)
CAMERA = {"width": 752, "height": 480, "fx": 450.0, "fy": 450.0, "cx": 375.5, "cy": 239.5}
UNKNOWN_UAV2 = "fuse.initial.unknown={uav2: {offset_m: [8.0, -6.0, 0.0], yaw_offset_rad: 0.2}}"


def _one_vehicle(sim: Path, vehicle: str, run: Path) -> Path:
    """A run directory holding only `vehicle` of the simulation `sim` (links)."""
    (run / "features").mkdir(parents=True)
    os.symlink(sim / "features" / f"{vehicle}.npz", run / "features" / f"{vehicle}.npz")
    os.symlink(sim / f"{vehicle}.mcap", run / f"{vehicle}.mcap")
    os.symlink(sim / "truth", run / "truth")
    return run


@pytest.fixture(scope="module")
def worlds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The small two-UAV scenario (landmark mode, 6 s) in two worlds (seeds 3 and 4), and in
    each a run of uav1 alone, fused: its map is the prior."""
    from cvslam_cli.cli import main

    root = tmp_path_factory.mktemp("prior")
    path = small_uav_scenario(
        root, mode="landmarks", **{f"vehicles.{v}.camera.{k}": x for v in ("uav1", "uav2")
                                   for k, x in CAMERA.items()}
    )  # fmt: skip
    out = {}
    for seed in (3, 4):
        sim = root / f"sim{seed}"
        simulate(load_scenario(path, seed=seed), sim)
        run = _one_vehicle(sim, "uav1", root / f"uav1_{seed}")
        with pytest.raises(SystemExit) as exc:
            main(["-q", "fuse", str(run)])
        assert exc.value.code in (0, None)
        out[f"sim{seed}"], out[f"map{seed}"] = sim, run
    return out


def _summary(run: Path) -> dict:
    return yaml.safe_load((run / "run.yaml").read_text())["stages"]["fuse"]["summary"]


def test_different_seeds_are_different_worlds(worlds):
    """The foreign map's check means something only if another seed is another place."""
    a = load_map(worlds["map3"] / "fuse" / "map.npz")
    b = load_map(worlds["map4"] / "fuse" / "map.npz")
    # each of a's landmarks is farther from every one of b's than the association accepts
    # (fuse.association.max_descriptor_distance, 350; a re-observation is ~70 away)
    d = np.linalg.norm(a.descriptor[:, None, :].astype(float) - b.descriptor[None], axis=2)
    assert d.min() > 350 and len(a) > 50 and len(b) > 50
    assert not np.array_equal(
        np.load(worlds["sim3"] / "truth" / "world.npz")["elevation_m"],
        np.load(worlds["sim4"] / "truth" / "world.npz")["elevation_m"],
    )


def test_prior_map_round_trip_seeds_the_book_and_keeps_sessions(worlds, tmp_path):
    """The map read back is the map written; seeded into a book it is out of the state and
    unobserved by this session; the merged map keeps the prior's rows, vehicles and
    sessions, the new landmarks one session more."""
    path, a = load_prior_map(str(worlds["map3"]))
    assert path == worlds["map3"] / "fuse" / "map.npz"
    assert np.all(a.session == 0) and a.vehicles == ("uav1",)
    save_map(tmp_path / "again.npz", a)
    _, b = load_prior_map(str(tmp_path / "again.npz"))
    for name in ("p_nav_m", "cov_nav_m2", "descriptor", "last_seen_ns", "session"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    prior = PriorMap(a, SlamSettings(prior_map_inflation=4.0))
    # the common offset's covariance: the smallest archived variance per axis, inflated
    var = np.diagonal(a.cov_nav_m2, axis1=1, axis2=2)
    np.testing.assert_allclose(np.diag(prior.offset_covariance()), 4.0 * var.min(axis=0))
    book = LandmarkBook(1)
    prior.seed(book)
    n = len(a)
    assert book.count == n and len(book.slot_ids) == 0 and prior.session == 1
    assert np.all(book.last_seen_ns[:n] == NEVER_NS) and np.all(book.observers[:n] == 0)
    np.testing.assert_array_equal(book.p_nav_m[:n], a.p_nav_m)
    # one new landmark seen by this session's uav2; prior landmark 0 observed again
    book.add(a.descriptor[:1], 0, 7, np.array([-1]), np.array([[0.0, 0.0, -1.0]]))
    book.observe(np.array([0]), 0, 9, np.array([[0.0, 0.0, -1.0]]), np.array([10.0]))
    merged = prior.merged_archive(book.archive(["uav2"], a.coordinates))
    assert merged.vehicles == ("uav1", "uav2") and len(merged) == n + 1
    assert list(merged.session[[0, n]]) == [0, 1]
    assert merged.last_seen_ns[0, 1] == 9 and merged.last_seen_ns[0, 0] == a.last_seen_ns[0, 0]
    assert merged.last_seen_ns[n, 0] == NEVER_NS and merged.observers()[0] == "uav1;uav2"


def test_uav2_is_localised_in_uav1s_prior_map_and_maps_on(worlds, tmp_path, cvslam):
    """UAV2 alone, from a prior 10 m and 11 degrees off, in the map UAV1 made in an earlier
    run: localised within seconds (the first PnP fit at ~2.8 s, when it overlaps the map) on
    prior-map landmarks, then tracked; the outputs tell the prior's landmarks (session 0)
    from its own (session 1)."""
    run = _one_vehicle(worlds["sim3"], "uav2", tmp_path / "uav2")
    r = cvslam("-v", "fuse", run, "--prior-map", worlds["map3"], "--set", UNKNOWN_UAV2)
    assert r.code == 0, r.err
    assert "localised in the map" in r.err and "prior-map landmarks brought" in r.err
    s = _summary(run)
    v = s["vehicles"]["uav2"]
    print(
        f"\nuav2 localised in the prior map {v['localised_after_s']:.2f} s after its start on "
        f"{v['localised_inliers']} inliers, {v['prior_landmarks']} prior landmarks used"
    )
    assert 0 < v["localised_after_s"] < 4.5 and v["localised_inliers"] >= 12
    assert v["prior_landmarks"] >= 12 and s["prior_map"]["observed_again"] > 20
    events = pd.read_csv(run / "fuse" / "events.csv")
    loc = events[events.event == "localisation"]
    assert len(loc) == 1 and "prior map" in loc.detail.iloc[0]
    tl = pd.read_csv(run / "fuse" / "timeline.csv")
    assert tl.prior.sum() > 50 and not tl.localised.iloc[0] and tl.localised.iloc[-1]
    est = read_tum(run / "fuse" / "uav2.tum")
    truth = read_tum(worlds["sim3"] / "truth" / "uav2.tum")
    err = np.linalg.norm(
        est.p_nav_m - interpolate_positions(truth.stamps_ns, truth.p_nav_m, est.stamps_ns), axis=1
    )
    after = est.stamps_ns >= est.stamps_ns[0] + v["localised_after_s"] * 1e9
    rmse_after = np.sqrt(np.mean(err[after] ** 2))
    print(f"error at the start {err[0]:.1f} m, RMSE after {rmse_after:.2f} m")
    assert err[0] > 8 and rmse_after < 1.5
    mp = read_map_csv(run / "fuse" / "map.csv")
    n_prior = s["prior_map"]["landmarks"]
    assert list(np.unique(mp.session)) == [0, 1] and np.sum(mp.session == 0) == n_prior
    assert sum(o == "uav1;uav2" for o in mp.observers) == s["prior_map"]["observed_again"]
    assert load_map(run / "fuse" / "map.npz").vehicles == ("uav1", "uav2")
    # the prior map's content is an input: changed in place, the stage is run again
    prior = tmp_path / "prior.npz"
    shutil.copyfile(worlds["map3"] / "fuse" / "map.npz", prior)
    args = ("fuse", run, "--force", "--prior-map", prior, "--set", UNKNOWN_UAV2)
    assert cvslam(*args).code == 0
    assert "up to date" in cvslam(*args[:2], *args[3:]).err
    shutil.copyfile(worlds["map4"] / "fuse" / "map.npz", prior)
    r = cvslam(*args[:2], *args[3:])
    assert r.code == 0 and "up to date" not in r.err
    assert _summary(run)["prior_map"]["landmarks"] == len(load_map(prior))


def test_a_map_of_another_world_never_localises(worlds, tmp_path, cvslam):
    """UAV2 of world 3 in the map of world 4: never localised, and with a known initial
    pose no prior landmark is ever taken for one of its own."""
    run = _one_vehicle(worlds["sim3"], "uav2", tmp_path / "uav2")
    r = cvslam("fuse", run, "--prior-map", worlds["map4"], "--set", UNKNOWN_UAV2)
    assert r.code == 0, r.err
    assert "never localised" in r.err
    v = _summary(run)["vehicles"]["uav2"]
    assert v["localised_after_s"] is None and v["prior_landmarks"] == 0
    r = cvslam("fuse", run, "--force", "--prior-map", worlds["map4"])
    assert r.code == 0, r.err
    s = _summary(run)
    assert s["vehicles"]["uav2"]["prior_landmarks"] == 0 and s["prior_map"]["observed_again"] == 0


def test_a_map_with_the_right_descriptors_in_the_wrong_places_never_localises(
    worlds, tmp_path, cvslam
):
    """The hard case of a foreign map, where descriptors pair up (images of a similar
    texture): world 3's own map with its landmarks' positions shuffled. Every descriptor
    pair is then a geometric outlier, and the PnP inliers, the reprojection in both images
    and the same pose over consecutive frames must refuse it."""
    a = load_map(worlds["map3"] / "fuse" / "map.npz")
    perm = np.random.default_rng(0).permutation(len(a))
    shuffled = LandmarkArchive(
        **{**vars(a), "p_nav_m": a.p_nav_m[perm], "cov_nav_m2": a.cov_nav_m2[perm]}
    )
    save_map(tmp_path / "shuffled.npz", shuffled)
    run = _one_vehicle(worlds["sim3"], "uav2", tmp_path / "uav2")
    r = cvslam("fuse", run, "--prior-map", tmp_path / "shuffled.npz", "--set", UNKNOWN_UAV2)
    assert r.code == 0, r.err
    v = _summary(run)["vehicles"]["uav2"]
    assert v["localised_after_s"] is None and v["prior_landmarks"] == 0
    # with a known initial pose, nothing consistent is found either
    r = cvslam("fuse", run, "--force", "--prior-map", tmp_path / "shuffled.npz")
    assert r.code == 0, r.err
    assert _summary(run)["vehicles"]["uav2"]["prior_landmarks"] == 0


def _one_line(r, *words: str) -> None:
    assert r.code == 1 and r.err.count("\n") == 1, r.err
    for w in words:
        assert w in r.err, r.err


def test_bad_prior_maps_are_one_clear_error(worlds, tmp_path, cvslam):
    run = _one_vehicle(worlds["sim3"], "uav2", tmp_path / "uav2")
    _one_line(cvslam("fuse", run, "--prior-map", tmp_path / "nope"), "fuse.prior_map", "nope")
    (tmp_path / "empty").mkdir()
    _one_line(cvslam("fuse", run, "--prior-map", tmp_path / "empty"), "fuse/map.npz")
    src = dict(np.load(worlds["map3"] / "fuse" / "map.npz"))
    save_npz(tmp_path / "v9.npz", {**src, "version": np.array(9)})
    _one_line(cvslam("fuse", run, "--prior-map", tmp_path / "v9.npz"), "v9.npz", "version 9")
    save_npz(tmp_path / "enu.npz", {**src, "nav_frame": np.array("ENU")})
    _one_line(cvslam("fuse", run, "--prior-map", tmp_path / "enu.npz"), "enu.npz", "ENU")
    (tmp_path / "text.npz").write_text("not a map")
    _one_line(cvslam("fuse", run, "--prior-map", tmp_path / "text.npz"), "text.npz")
    _one_line(
        cvslam("fuse", run, "--single", "--set", f"fuse.prior_map={worlds['map3']}"),
        "--single",
    )
    # the run's own output as its prior: it would be replaced
    assert cvslam("fuse", run).code == 0
    _one_line(cvslam("fuse", run, "--force", "--prior-map", run), "own output")
    with pytest.raises(CvslamError, match="no such run directory"):
        load_prior_map(str(tmp_path / "missing.npz"))


def test_sessions_round_trip_and_older_files_read_as_session_0(worlds, tmp_path):
    """map.npz and map.csv keep each landmark's session; files written before sessions
    existed (no `session` entry or column) read as one session, 0."""
    a = load_map(worlds["map3"] / "fuse" / "map.npz")
    sessions = np.arange(len(a)) % 3
    b = LandmarkArchive(**{**vars(a), "session": sessions})
    save_map(tmp_path / "map.npz", b)
    np.testing.assert_array_equal(load_map(tmp_path / "map.npz").session, sessions)
    write_map_csv(tmp_path / "map.csv", b.landmark_map())
    np.testing.assert_array_equal(read_map_csv(tmp_path / "map.csv").session, sessions)
    old = {k: v for k, v in np.load(tmp_path / "map.npz").items() if k != "session"}
    save_npz(tmp_path / "old.npz", old)
    assert not load_map(tmp_path / "old.npz").session.any()
    pd.read_csv(tmp_path / "map.csv").drop(columns="session").to_csv(
        tmp_path / "old.csv", index=False
    )
    assert not read_map_csv(tmp_path / "old.csv").session.any()


def test_a_refined_map_is_a_prior_map(worlds, tmp_path, cvslam):
    """`cvslam refine` of UAV1's run writes a map file (its landmarks at the batch solution,
    with their marginals, and re-association's new points with descriptors) that a later run
    takes as its prior map (`--prior-map RUN/fuse_refined`): UAV2 of the same world uses its
    landmarks; UAV2 of another world never does."""
    run1 = tmp_path / "uav1"
    shutil.copytree(worlds["map3"], run1, symlinks=True)
    r = cvslam("refine", run1)
    assert r.code == 0, r.err
    refined, source = (
        load_map(run1 / "fuse_refined" / "map.npz"),
        load_map(run1 / "fuse" / "map.npz"),
    )
    # the refined landmarks and the new points are the batch's, the rest (those the batch
    # could not constrain; none on this run since its start is exact) the filter's
    assert refined.batch[len(source) :].all() and not source.batch.any()
    assert 0.5 * len(source) < refined.batch[: len(source)].sum() <= len(source)
    mp = read_map_csv(run1 / "fuse_refined" / "map.csv")
    assert np.array_equal(refined.landmark_id[: len(source)], source.landmark_id)
    assert len(refined) > len(source)  # the tracks' points
    assert np.array_equal(refined.landmark_id, mp.landmark_id)
    np.testing.assert_allclose(refined.p_nav_m, mp.p_nav_m)
    std = np.sqrt(np.diagonal(refined.cov_nav_m2, axis1=1, axis2=2))
    np.testing.assert_allclose(std, mp.std_m, rtol=1e-12)  # map.csv summarises map.npz
    np.testing.assert_array_equal(refined.session, mp.session)
    new = slice(len(source), None)
    assert np.all(np.linalg.eigvalsh(refined.cov_nav_m2[new]) > 0)
    assert np.all(refined.descriptor[new].any(axis=1)) and np.all(refined.n_observations[new] >= 2)
    assert set(refined.observers()[new]) == {"uav1"}
    # map.csv says the same of them: observers, observation counts, first and last times
    assert list(mp.observers[new]) == list(refined.observers()[new])
    np.testing.assert_array_equal(mp.n_observations[new], refined.n_observations[new])
    np.testing.assert_array_equal(mp.first_seen_ns[new], refined.first_seen_ns[new])
    np.testing.assert_array_equal(mp.last_seen_ns[new], refined.last_seen_ns[new].max(axis=1))
    # the marginals are honest: the landmarks' NEES against the simulator's truth
    truth = pd.read_csv(worlds["sim3"] / "truth" / "landmarks.csv").set_index("id")
    known = refined.true_id >= 0
    e = refined.p_nav_m[known] - truth.loc[refined.true_id[known], ["x_m", "y_m", "z_m"]].to_numpy()
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(refined.cov_nav_m2[known]), e)
    print(f"\nrefined map: {len(refined)} landmarks, NEES mean {nees.mean():.2f} (3 expected)")
    assert 0.3 < nees.mean() < 6.0
    for sim, used in (("sim3", True), ("sim4", False)):
        run = _one_vehicle(worlds[sim], "uav2", tmp_path / f"uav2_{sim}")
        r = cvslam("fuse", run, "--prior-map", run1 / "fuse_refined")
        assert r.code == 0, r.err
        s = _summary(run)
        assert s["prior_map"]["landmarks"] == len(refined)
        assert (s["vehicles"]["uav2"]["prior_landmarks"] > 12) == used, sim


def test_a_ground_robot_of_unknown_pose_is_localised_in_a_prior_map(tmp_path, cvslam):
    """A ground robot's state has no height (3-DOF odometry): the check of the pose found
    against its prior is over the axes it has (its height variance is 0; the check's solve
    of the whole position covariance was a traceback)."""
    from cvslam_cli.sim.scenario import SCENARIO_DIR

    sc = load_scenario(SCENARIO_DIR / "ugv2_yard.yaml", ["mode=landmarks", "duration_s=20"], seed=2)
    first = simulate(sc, tmp_path / "first").out_dir
    again = tmp_path / "again"
    shutil.copytree(first, again)
    for run in (first, again):
        (run / "robot2.mcap").unlink()
        for f in (run / "features").glob("robot2*"):
            f.unlink()
    assert cvslam("-q", "fuse", first).code == 0
    unknown = "fuse.initial.unknown={robot1: {offset_m: [1.0, -1.0, 0.0], yaw_offset_rad: 0.05}}"
    res = cvslam("fuse", again, "--set", f"fuse.prior_map={first}", "--set", unknown)
    assert res.code == 0, res.err
    summary = yaml.safe_load((again / "run.yaml").read_text())["stages"]["fuse"]["summary"]
    robot = summary["vehicles"]["robot1"]
    assert robot["localised_after_s"] is not None and robot["localised_after_s"] < 2.0
    assert robot["rmse_m"] < 0.5
