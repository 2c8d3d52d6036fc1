"""`cvslam simulate` end to end on small scenarios: logs, truth, determinism, bad input."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import ConfigError, CvslamError
from cvslam_cli.geometry.rotations import quat_xyzw_to_matrix
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.records.log import ImuSample, OdometryRecord, PoseRecord, StereoFrame
from cvslam_cli.sim.scenario import SCENARIO_DIR, load_scenario
from cvslam_cli.sim.stage import run
from cvslam_cli.sim.strapdown import integrate_strapdown
from cvslam_cli.sim.vehicles import build_path
from tests.scenarios import small_uav_scenario


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sim")
    sc = load_scenario(small_uav_scenario(tmp))
    return run(sc, tmp / "out", workers=2), sc


def test_outputs_and_logs_read_back(small_run):
    summary, sc = small_run
    out = summary.out_dir
    for name in ("uav1", "uav2"):
        assert (out / f"{name}.mcap").is_file()
        assert (out / "truth" / f"{name}.tum").is_file()
        assert (out / "truth" / f"{name}_imu.npz").is_file()
    assert (out / "truth" / "world.npz").is_file() and (out / "scenario.yaml").is_file()
    assert load_scenario(out / "scenario.yaml") == sc  # the copy reproduces the run
    logs = LogSet(
        [McapLogSource(out / "uav1.mcap"), McapLogSource(out / "uav2.mcap")], load_config().logs
    )
    assert sorted(logs.vehicles) == ["uav1", "uav2"]
    rig = logs.rig("uav1")
    assert rig.baseline_m == pytest.approx(1.5) and rig.rectified
    recs = list(logs.records())
    frames = {
        v: [r for r in recs if isinstance(r, StereoFrame) and r.vehicle == v]
        for v in ("uav1", "uav2")
    }
    imu = [r for r in recs if isinstance(r, ImuSample) and r.vehicle == "uav1"]
    assert len(frames["uav1"]) == 31 and len(frames["uav2"]) == 26  # 5 Hz, uav2 starts at 1 s
    assert len(imu) == 1201
    assert frames["uav1"][0].left.image.shape == (120, 188)
    assert frames["uav2"][0].stamp_ns - frames["uav1"][0].stamp_ns == 1_000_000_000
    assert 20 < np.mean([f.left.image.mean() for f in frames["uav1"]]) < 235
    assert logs.stats["uav1"].unpaired_left == 0


def test_same_seed_is_byte_identical_other_seed_differs(small_run, tmp_path):
    summary, sc = small_run
    again = run(sc, tmp_path / "again", workers=1)  # also: worker count does not matter
    assert _digest(summary.out_dir) == _digest(again.out_dir)
    other = run(load_scenario(small_uav_scenario(tmp_path), seed=4), tmp_path / "other")
    a, b = _digest(summary.out_dir), _digest(other.out_dir)
    assert a["uav1.mcap"] != b["uav1.mcap"] and a["truth/world.npz"] != b["truth/world.npz"]


def _records(path: Path, cls):
    logs = LogSet([McapLogSource(path)], load_config().logs)
    return [r for r in logs.records() if isinstance(r, cls)]


def test_noise_free_imu_in_the_log_integrates_to_the_truth(tmp_path):
    """The IMU written to the MCAP (not only the model) is exact: strapdown integration of
    the logged samples stays on the logged ground truth to millimetres."""
    path = small_uav_scenario(tmp_path)
    zero = {
        "gyro_noise_density": 0.0,
        "gyro_random_walk": 0.0,
        "accel_noise_density": 0.0,
        "accel_random_walk": 0.0,
        "gyro_bias_initial_sigma": 0.0,
        "accel_bias_initial_sigma": 0.0,
    }
    sc = load_scenario(
        path,
        [
            f"vehicles.uav1.imu={zero}".replace("'", ""),
            "vehicles.uav1.ground_truth_at=imu",
            "mode=landmarks",
        ],
        duration_s=20.0,
    )
    out = run(sc, tmp_path / "exact").out_dir
    imu = _records(out / "uav1.mcap", ImuSample)
    gt = _records(out / "uav1.mcap", PoseRecord)
    t = np.array([s.stamp_ns for s in imu]) * 1e-9
    gyro = np.array([s.gyro_rad_s for s in imu])
    acc = np.array([s.accel_m_s2 for s in imu])
    p_true = np.array([g.p_m for g in gt])
    C0 = quat_xyzw_to_matrix(gt[0].q_xyzw)

    path_obj = build_path("uav1", sc.vehicles["uav1"], sc.duration_s, "test")
    v0 = path_obj.sample(np.array([0.0])).v_nav_m_s[0]
    p, _, _ = integrate_strapdown(t - t[0], gyro, acc, p_true[0], v0, C0, np.array([0, 0, 9.80665]))
    err = np.linalg.norm(p - p_true, axis=1)
    assert err.max() < 0.005, err.max()


def test_dead_reckoning_drifts_superlinearly(tmp_path):
    path = small_uav_scenario(tmp_path)
    opts = ["vehicles.uav1.ground_truth_at=imu", "mode=landmarks"]
    sc = load_scenario(path, opts, duration_s=30.0)
    errors = []
    for seed in range(2):
        out = run(
            load_scenario(path, opts, seed=seed, duration_s=30.0), tmp_path / f"dr{seed}"
        ).out_dir
        imu = _records(out / "uav1.mcap", ImuSample)
        gt = _records(out / "uav1.mcap", PoseRecord)
        t = np.array([s.stamp_ns for s in imu]) * 1e-9
        v0 = (
            build_path("uav1", sc.vehicles["uav1"], sc.duration_s, "t")
            .sample(np.array([0.0]))
            .v_nav_m_s[0]
        )
        p, _, _ = integrate_strapdown(
            t - t[0],
            np.array([s.gyro_rad_s for s in imu]),
            np.array([s.accel_m_s2 for s in imu]),
            gt[0].p_m,
            v0,
            quat_xyzw_to_matrix(gt[0].q_xyzw),
            np.array([0, 0, 9.80665]),
        )
        errors.append(np.linalg.norm(p - np.array([g.p_m for g in gt]), axis=1))
    err = np.mean(errors, axis=0)
    t = np.arange(len(err)) / 200.0
    e10, e30 = err[np.searchsorted(t, 10.0)], err[-1]
    assert e30 > 10.0  # visibly drifting: tens of metres after 30 s
    assert e30 / e10 > 3**1.8  # superlinear: about quadratic or faster from 10 s to 30 s


def test_landmark_mode_writes_features_consistent_with_truth(tmp_path):
    # pixel noise small against the disparity (~2 px here), where the linearised covariance
    # of the triangulation holds
    sc = load_scenario(
        small_uav_scenario(tmp_path), ["mode=landmarks", "landmarks.pixel_noise_px=0.1"]
    )
    out = run(sc, tmp_path / "lm").out_dir
    assert not list(out.glob("truth/*_depth.npz"))
    truth = np.loadtxt(out / "truth" / "landmarks.csv", delimiter=",", skiprows=1)
    fs, meta = load_features(out / "features" / "uav1.npz")
    assert meta["producer"].startswith("cvslam simulate")
    assert fs.n_frames == 31 and fs.match_offsets[-1] > 31 * 20
    gt = _records(out / "uav1.mcap", PoseRecord)
    assert [g.stamp_ns for g in gt] == fs.frame_stamp_ns.tolist()
    nees, outliers = [], 0
    T_body_left = fs.rig.T_body_cam[0]
    for i, g in enumerate(gt):
        sl = fs.frame_matches(i)
        ids = fs.match_landmark_id[sl]
        outliers += int(np.sum(ids == -2))
        good = ids >= 0
        T_nav_body = np.eye(4)
        T_nav_body[:3, :3] = quat_xyzw_to_matrix(g.q_xyzw)
        T_nav_body[:3, 3] = g.p_m
        T = T_nav_body @ T_body_left
        p_cam_true = (truth[ids[good], 1:4] - T[:3, 3]) @ T[:3, :3]
        diff = fs.match_p_cam_m[sl][good] - p_cam_true
        cov = fs.match_cov_cam_m2[sl][good]
        nees.extend(np.einsum("ni,nij,nj->n", diff, np.linalg.inv(cov), diff))
    assert 2.5 < np.mean(nees) < 3.6  # consistent 3-D covariance (chi-square, 3 dof)
    total = int(fs.match_offsets[-1])
    assert 0.01 < outliers / total < 0.06  # outlier_fraction 0.03
    assert np.all(fs.match_ratio[fs.match_landmark_id >= 0] < 1.0)


def test_observer_offsets_displace_each_vehicles_view_of_a_landmark(tmp_path):
    """`landmarks.observer_offset_m`: every observation of a landmark by one vehicle sits on
    the landmark displaced by that vehicle's own offset, the same in every frame, drawn with
    the deviation asked and independent of the other vehicle's (pixel noise 0: the stereo
    points are the displaced points exactly)."""
    sigma = 0.3
    sets = ["mode=landmarks", "landmarks.outlier_fraction=0", "landmarks.pixel_noise_px=0",
            f"landmarks.observer_offset_m={sigma}"]  # fmt: skip
    out = run(load_scenario(small_uav_scenario(tmp_path), sets), tmp_path / "lm").out_dir
    truth = np.loadtxt(out / "truth" / "landmarks.csv", delimiter=",", skiprows=1)
    offsets = {}
    for vehicle in ("uav1", "uav2"):
        fs, _ = load_features(out / "features" / f"{vehicle}.npz")
        gt = _records(out / f"{vehicle}.mcap", PoseRecord)
        by_id: dict[int, list[np.ndarray]] = {}
        for i, g in enumerate(gt):
            sl = fs.frame_matches(i)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = quat_xyzw_to_matrix(g.q_xyzw), g.p_m
            T = T @ fs.rig.T_body_cam[0]
            ids = fs.match_landmark_id[sl]
            p_nav = fs.match_p_cam_m[sl] @ T[:3, :3].T + T[:3, 3]
            for lid, d in zip(ids, p_nav - truth[ids, 1:4], strict=True):
                by_id.setdefault(int(lid), []).append(d)
        seen = [np.array(d) for d in by_id.values() if len(d) >= 3]
        assert len(seen) > 30
        assert max(np.abs(d - d[0]).max() for d in seen) < 1e-6  # fixed over the mission
        offsets[vehicle] = {lid: np.array(d)[0] for lid, d in by_id.items()}
        spread = np.std(np.concatenate([np.array(d)[:1] for d in seen]), axis=0)
        assert np.all((0.6 * sigma < spread) & (spread < 1.4 * sigma))  # per nav axis
    shared = sorted(set(offsets["uav1"]) & set(offsets["uav2"]))
    assert len(shared) > 10
    a = np.array([offsets["uav1"][i] for i in shared]).ravel()
    b = np.array([offsets["uav2"][i] for i in shared]).ravel()
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.4  # each vehicle its own offsets


def test_lookalikes_imitate_a_landmark_in_view_near_its_own_pixel(tmp_path):
    """`landmarks.lookalike_fraction`: wrong matches (id -2) whose descriptor is a landmark's
    (perturbed as a true observation's) and whose pixels lie within the offset of that
    landmark's true match in the frame, at its disparity: what the filter's gate and
    descriptor test cannot tell from the landmark, unlike the random outliers."""
    sets = ["mode=landmarks", "landmarks.outlier_fraction=0", "landmarks.pixel_noise_px=0.2",
            "landmarks.lookalike_fraction=0.2", "landmarks.lookalike_offset_px=6"]  # fmt: skip
    out = run(load_scenario(small_uav_scenario(tmp_path), sets), tmp_path / "lm").out_dir
    fs, _ = load_features(out / "features" / "uav1.npz")
    ids = fs.match_landmark_id
    wrong, total = int(np.sum(ids == -2)), len(ids)
    assert 0.12 < wrong / total < 0.28  # 20 % of the matches, fewer where pushed off the image
    near, desc_d, true_d = [], [], []
    for i in range(fs.n_frames):
        sl = fs.frame_matches(i)
        z = np.column_stack(
            [fs.left_uv_px[fs.match_left[sl]], fs.right_uv_px[fs.match_right[sl]]]
        )  # fmt: skip
        desc = fs.left_desc[fs.match_left[sl]].astype(float)
        fid = ids[sl]
        true, bad = np.flatnonzero(fid >= 0), np.flatnonzero(fid == -2)
        for b in bad:
            d = np.linalg.norm(desc[true] - desc[b], axis=1)
            j = true[np.argmin(d)]  # the landmark imitated, by descriptor
            desc_d.append(d.min())
            near.append(np.abs(z[b] - z[j]).max())
            assert abs((z[b, 0] - z[b, 2]) - (z[j, 0] - z[j, 2])) < 2.0  # its disparity
        for t in true[:5]:  # two true observations of different landmarks, for scale
            others = true[true != t]
            true_d.append(np.linalg.norm(desc[others] - desc[t], axis=1).min())
    # found among the frame's true matches (the imitated landmark can be missed: most are)
    assert np.mean(np.array(desc_d) < 0.5 * np.median(true_d)) > 0.7
    hit = np.array(desc_d) < 0.5 * np.median(true_d)
    assert np.all(np.array(near)[hit] < 6.0 + 1.5)  # within the offset (+ pixel noise)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"vehicles.uav1.speed_m_s": -1.0}, "vehicles.uav1.speed_m_s: expected a number > 0.0"),
        ({"vehicles.uav1.camera.rate_hz": -5.0}, "vehicles.uav1.camera.rate_hz: expected"),
        ({"vehicles.uav1.colour": "red"}, "vehicles.uav1.colour: unknown key"),
        (
            {"vehicles.uav2.waypoints_nav_m": [[140, 0, -80], [200, 0, -80], [200, 100, -80]]},
            "vehicles.uav2.waypoints_nav_m: the path leaves the terrain",
        ),
        (
            {"vehicles.uav1.camera.mount": "forward", "vehicles.uav1.camera.tilt_deg": -30.0},
            "vehicles.uav1.camera: the camera sees the ground in only",
        ),
        (
            {"vehicles.uav1.waypoints_nav_m": [[0, 0, -80]]},
            "vehicles.uav1.waypoints_nav_m: expected at least 2 waypoints",
        ),
    ],
)
def test_bad_scenarios_give_one_line_naming_the_key(tmp_path, change, message):
    with pytest.raises(ConfigError) as exc:
        sc = load_scenario(small_uav_scenario(tmp_path, **change))
        run(sc, tmp_path / "bad")
    assert message in str(exc.value) and "\n" not in str(exc.value)
    assert not (tmp_path / "bad").exists() and not (tmp_path / "bad.partial").exists()


def test_existing_output_needs_force(tmp_path):
    sc = load_scenario(small_uav_scenario(tmp_path), ["mode=landmarks", "duration_s=2.0"])
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("precious")
    with pytest.raises(CvslamError, match="already exists"):
        run(sc, tmp_path / "out")
    assert (tmp_path / "out" / "keep.txt").read_text() == "precious"
    run(sc, tmp_path / "out", force=True)
    assert not (tmp_path / "out" / "keep.txt").exists()


def test_shipped_scenarios_load():
    for path in sorted(SCENARIO_DIR.glob("*.yaml")):
        sc = load_scenario(path)
        assert sc.vehicles, path


def test_ugv_odometry_drifts(tmp_path):
    sc = load_scenario(SCENARIO_DIR / "ugv2_yard.yaml", ["mode=landmarks", "duration_s=30"])
    out = run(sc, tmp_path / "yard").out_dir
    for name in sc.vehicles:
        odo = _records(out / f"{name}.mcap", OdometryRecord)
        gt = _records(out / f"{name}.mcap", PoseRecord)
        assert len(odo) == int((30 - sc.vehicles[name].start_s) * 50) + 1
        p_odo = np.array([o.position_m[:2] for o in odo])
        t_odo = np.array([o.stamp_ns for o in odo])
        idx = np.searchsorted(t_odo, gt[-1].stamp_ns)
        final = np.linalg.norm(p_odo[idx] - gt[-1].p_m[:2])
        dist = np.sum(np.linalg.norm(np.diff(np.array([g.p_m for g in gt]), axis=0), axis=1))
        assert final > 0.01 * dist  # wheel odometry drifts measurably


def test_non_rectified_rig_and_true_depth(tmp_path):
    sc = load_scenario(
        small_uav_scenario(tmp_path),
        ["vehicles.uav1.camera.rectified=false", "outputs.depth=true", "duration_s=2.0"],
    )
    out = run(sc, tmp_path / "nr").out_dir
    logs = LogSet([McapLogSource(out / "uav1.mcap")], load_config().logs)
    rig = logs.rig("uav1")
    assert not rig.rectified and rig.left.has_distortion
    assert rig.left.D[0] == pytest.approx(-0.25)
    R = rig.T_left_right[:3, :3]
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(0.94, abs=0.05)
    with np.load(out / "truth" / "uav1_depth.npz") as npz:
        names = sorted(npz.files)
        depth = npz[names[0]].astype(float)
    assert len(names) == 11 and depth.shape == (120, 188)
    gt = _records(out / "uav1.mcap", PoseRecord)[0]
    world = np.load(out / "truth" / "world.npz")
    # the depth at the image centre is the camera's height above the terrain (camera looks
    # nearly straight down); the terrain under the UAV is within the relief of the world
    agl = depth[60, 94]
    ground_z = gt.p_m[2] + agl
    assert -world["elevation_m"].max() - 1 < ground_z < -world["elevation_m"].min() + 1
    # the small test terrain is steep (20 m hills 80 m across): a few oblique corner rays of
    # the distorted camera are ambiguous and marked invalid (NaN) rather than guessed
    assert np.isfinite(depth).mean() > 0.95


def test_duration_stretches_the_same_mission(tmp_path):
    base = load_scenario(SCENARIO_DIR / "uav2_paper.yaml")
    long = load_scenario(SCENARIO_DIR / "uav2_paper.yaml", duration_s=4 * base.duration_s)
    for name, v in base.vehicles.items():
        w = long.vehicles[name]
        assert w.speed_m_s == pytest.approx(v.speed_m_s / 4)
        assert w.start_s == pytest.approx(v.start_s * 4)
        assert w.waypoints_nav_m == v.waypoints_nav_m and w.camera == v.camera
        a = build_path(name, v, base.duration_s, "t")
        b = build_path(name, w, long.duration_s, "t")
        t = np.linspace(v.start_s, base.duration_s, 7)
        np.testing.assert_allclose(b.sample(4 * t).p_nav_m, a.sample(t).p_nav_m, atol=1e-6)
