"""`cvslam fuse` end to end on a small simulated run (landmark mode): outputs, accuracy
against dead reckoning, covariance health, outlier rejection, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import yaml
from threadpoolctl import threadpool_limits

from cvslam_cli.config import load_config
from cvslam_cli.estimation import stage
from cvslam_cli.estimation.slam import Slam, dead_reckoning_track
from cvslam_cli.geometry.rotations import (
    interpolate_positions,
    matrix_to_euler_zyx,
    quat_xyzw_to_matrix,
)
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.fuse_files import load_pose_covariances, read_map_csv
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.map_file import load_map
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.records.poses import PoseTable
from tests.features.synthetic_frames import frames_of
from tests.scenarios import small_uav_scenario

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


# a consumer-grade IMU (10x the simulator's default noise) so that dead reckoning drifts
# visibly within the test's 12 s, and the filter told the same densities
SENSORS = {
    "camera": {"mount": "down", "width": 752, "height": 480, "fx": 450.0, "fy": 450.0,
               "cx": 375.5, "cy": 239.5, "baseline_m": 1.5, "rate_hz": 10.0},
    "imu": {"accel_noise_density": 0.02, "gyro_noise_density": 1.7e-3},
}  # fmt: skip
NOISE = ("--set", "fuse.motion.accel_noise_density=0.02",
         "--set", "fuse.motion.gyro_noise_density=0.0017")  # fmt: skip


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 12 s two-UAV landmark-mode simulation (features + logs), made once."""
    from cvslam_cli.cli import main

    tmp = tmp_path_factory.mktemp("fuse")
    sc = small_uav_scenario(
        tmp,
        duration_s=12.0,
        mode="landmarks",
        **{f"vehicles.{v}.{k}": val for v in ("uav1", "uav2") for k, val in SENSORS.items()},
    )
    out = tmp / "sim"
    with pytest.raises(SystemExit) as exc:
        main(["-q", "simulate", str(sc), "-o", str(out)])
    assert exc.value.code in (0, None)
    return out


def _copy(sim_run: Path, tmp_path: Path) -> Path:
    run = tmp_path / "run"
    shutil.copytree(sim_run, run)
    return run


def _inputs(run: Path, *overrides: str):
    cfg = load_config((), [*NOISE[1::2], *overrides])
    feats = {v: load_features(run / "features" / f"{v}.npz")[0] for v in ("uav1", "uav2")}
    logs = LogSet([McapLogSource(run / f"{v}.mcap") for v in ("uav1", "uav2")], cfg.logs)
    inputs, truth = stage.build_inputs(cfg, feats, logs)
    return cfg, inputs, truth


def test_fuse_writes_every_output_and_beats_dead_reckoning(sim_run, tmp_path, cvslam):
    run = _copy(sim_run, tmp_path)
    r = cvslam("fuse", run, *NOISE)
    assert r.code == 0, r.err
    out = run / "fuse"
    names = {p.name for p in out.iterdir()}
    for v in ("uav1", "uav2"):
        assert {f"{v}.tum", f"{v}_deadreckoning.tum", f"{v}_pose_cov.npz"} <= names
    assert {"map.csv", "map.ply", "timeline.csv", "events.csv", "result.mcap"} <= names
    assert not (run / "fuse.partial").exists()
    summary = yaml.safe_load((run / "run.yaml").read_text())["stages"]["fuse"]["summary"]
    # the default measures it (the simulator's 0.5 px)
    assert summary["pixel_sigma_px"]["source"] == "measured"
    assert summary["pixel_sigma_px"]["value"] == pytest.approx(0.5, rel=0.08)
    # what auto chose for these two IMU vehicles, per vehicle
    assert summary["landmark_coordinates"] == {"uav1": "inverse_depth", "uav2": "inverse_depth"}
    assert summary["observability_constrained"] == {"uav1": True, "uav2": True}
    assert summary["max_updates_per_frame"] == {"uav1": 60, "uav2": 60}
    assert summary["target_tracked"] == {"uav1": 60, "uav2": 60}
    for v in ("uav1", "uav2"):
        s = summary["vehicles"][v]
        assert s["model"] == "ins"
        # vision keeps the error small where the IMU alone drifts away
        assert s["final_error_m"] < 0.25 * s["final_error_deadreckoning_m"], s
        truth = read_tum(run / "truth" / f"{v}.tum")
        est = read_tum(out / f"{v}.tum")
        stamps, cov = load_pose_covariances(out / f"{v}_pose_cov.npz")
        np.testing.assert_array_equal(stamps, est.stamps_ns)
        assert np.all(np.isin(est.stamps_ns, truth.stamps_ns))
        # covariances stay symmetric positive definite over the run
        assert np.allclose(cov, np.swapaxes(cov, 1, 2))
        assert np.all(np.linalg.eigvalsh(cov)[:, 0] > 0)
    tl = pd.read_csv(out / "timeline.csv")
    assert set(tl.vehicle) == {"uav1", "uav2"}
    assert tl.stamp_ns.is_monotonic_increasing
    assert (tl.type1 > 0).mean() > 0.9 and tl.type3.sum() > 0
    # a frame of a team with IMUs updates up to 60 landmarks (fuse.map.max_updates_per_frame auto)
    updated = tl.type1 + tl.type2
    assert updated.max() == 60 and (updated > 30).mean() > 0.5
    assert (tl.landmarks_in_state <= 150 + 100).all()  # fuse.map: 2 vehicles
    mp = read_map_csv(out / "map.csv")
    assert len(mp) == tl.landmarks_mapped.iloc[-1]
    assert mp.in_state.sum() == tl.landmarks_in_state.iloc[-1]
    # the map file holds the same landmarks with their full covariances
    archive = load_map(out / "map.npz")
    summary_map = archive.landmark_map()
    np.testing.assert_array_equal(summary_map.p_nav_m, mp.p_nav_m)
    np.testing.assert_array_equal(summary_map.std_m, mp.std_m)
    assert summary_map.observers == mp.observers
    assert np.all(np.linalg.eigvalsh(archive.cov_nav_m2)[:, 0] > 0)
    assert np.all(archive.evicted_ns[~archive.in_state] > 0)  # every landmark out was evicted
    # the same inputs and config: the stage is skipped
    before = (out / "uav1.tum").stat().st_mtime_ns
    assert cvslam("fuse", run, *NOISE).code == 0
    assert (out / "uav1.tum").stat().st_mtime_ns == before
    # another config is refused without --force
    r = cvslam("fuse", run, *NOISE, "--set", "fuse.map.max_landmarks=100")
    assert r.code == 1 and "different config" in r.err


def _yaml_list(values) -> str:
    return "[" + ", ".join(f"{x:.9f}" for x in values) + "]"


def test_initial_poses_from_the_config_replace_the_ground_truth(sim_run, tmp_path, cvslam):
    """Logs without ground truth: each vehicle's initial pose given in fuse.initial.poses
    (here the truth's first pose, velocity from its first two samples) gives the same
    accuracy as the log's ground truth, and the run's metadata says where it came from."""
    run = _copy(sim_run, tmp_path)
    poses = []
    for v in ("uav1", "uav2"):
        truth = read_tum(run / "truth" / f"{v}.tum")
        stamps = load_features(run / "features" / f"{v}.npz")[0].frame_stamp_ns
        i = int(np.searchsorted(truth.stamps_ns, stamps[0]))
        euler = matrix_to_euler_zyx(quat_xyzw_to_matrix(truth.q_nav_body_xyzw[i]))
        vel = (truth.p_nav_m[i + 1] - truth.p_nav_m[i]) / (
            (truth.stamps_ns[i + 1] - truth.stamps_ns[i]) * 1e-9
        )
        poses.append(
            f"{v}: {{position_m: {_yaml_list(truth.p_nav_m[i])}, "
            f"euler_rad: {_yaml_list(euler)}, velocity_m_s: {_yaml_list(vel)}}}"
        )
    r = cvslam("fuse", run, *NOISE, "--set", "fuse.initial.source=origin",
               "--set", "fuse.initial.poses={" + ", ".join(poses) + "}")  # fmt: skip
    assert r.code == 0, r.err
    summary = yaml.safe_load((run / "run.yaml").read_text())["stages"]["fuse"]["summary"]
    assert summary["initial_pose"] == {"uav1": "config", "uav2": "config"}
    for v in ("uav1", "uav2"):
        s = summary["vehicles"][v]
        assert s["final_error_m"] < 0.25 * s["final_error_deadreckoning_m"], s
    r = cvslam("fuse", run, "--force", "--set", "fuse.initial.poses={uav7: {}}")
    assert r.code == 1 and "fuse.initial.poses: no vehicle uav7" in r.err


def test_single_and_ekf_runs_go_to_their_own_folders(sim_run, tmp_path, cvslam):
    run = _copy(sim_run, tmp_path)
    r = cvslam("fuse", run, "--single", "--filter", "ekf", *NOISE)
    assert r.code == 0, r.err
    out = run / "fuse_ekf_single"
    assert (out / "uav1.tum").exists() and (out / "uav2.tum").exists()
    mp = read_map_csv(out / "map.csv")
    # each vehicle alone: no landmark observed by both
    assert not any(";" in o for o in mp.observers)
    events = pd.read_csv(out / "events.csv")
    assert "cross_vehicle" not in set(events.event)


def test_wrong_matches_never_become_landmarks_and_associations_are_right(sim_run):
    """The simulator injects 3 % wrong stereo matches (true id -2): the candidate
    confirmation keeps them out of the map; the filter stays consistent in NIS."""
    cfg, inputs, truth = _inputs(sim_run)
    with threadpool_limits(limits=1, user_api="blas"):
        res = Slam(inputs[:1], stage.settings_for(cfg.fuse, "ekf", inputs[:1])).run()
    assert res.divergence is None
    assert np.sum(res.landmarks.true_id == -2) == 0
    assert np.sum(res.landmarks.true_id >= 0) == len(res.landmarks)
    tl = pd.DataFrame(res.timeline)
    upd = tl[tl.nis_dof > 0]
    assert 0.5 < (upd.nis / upd.nis_dof).mean() < 2.0
    # dead reckoning from the same start drifts far more than the filter
    tr, dr = res.tracks["uav1"], dead_reckoning_track(inputs[0])
    np.testing.assert_array_equal(tr.stamps_ns, dr.stamps_ns)
    gt = interpolate_positions(truth["uav1"].stamps_ns, truth["uav1"].p_nav_m, tr.stamps_ns)
    e = np.linalg.norm(tr.p_nav_m - gt, axis=1)
    e_dr = np.linalg.norm(dr.p_nav_m - gt, axis=1)
    assert e[-1] < 0.5 * e_dr[-1] and e.max() < 1.5


def test_the_pixel_noise_configured_measured_or_assumed(sim_run, caplog):
    """fuse.association.pixel_sigma_px: a number is used as it is; auto measures it from
    the vehicles' frames (the simulator's 0.5 px) and says so; frames that measure nothing
    (one frame each) fall back to FALLBACK_PIXEL_SIGMA_PX and say so."""
    cfg, inputs, _ = _inputs(sim_run, "fuse.association.pixel_sigma_px=0.7")
    assert stage.pixel_sigma(cfg.fuse, inputs) == stage.PixelSigma(0.7, "configured")
    cfg, inputs, _ = _inputs(sim_run, "fuse.association.pixel_sigma_px=auto")
    with caplog.at_level("INFO", logger="cvslam.fuse"):
        measured = stage.pixel_sigma(cfg.fuse, inputs)
    assert "pixel noise 0.5" in caplog.text or "pixel noise 0.4" in caplog.text
    assert "measured from" in caplog.text
    assert measured.source == "measured" and measured.noise is not None
    assert measured.sigma_px == pytest.approx(0.5, rel=0.08)
    assert measured.noise.pairs > 100  # both vehicles' frames
    one_frame = [SimpleNamespace(features=frames_of(0.0, ahead=True, frames=1)[0])]
    with caplog.at_level("WARNING", logger="cvslam.fuse"):
        assumed = stage.pixel_sigma(cfg.fuse, one_frame)  # type: ignore[arg-type]
    assert assumed == stage.PixelSigma(stage.FALLBACK_PIXEL_SIGMA_PX, "fallback")
    assert "measured no pixel noise" in caplog.text and "set it to a number" in caplog.text


def test_lookalikes_auto_bounds_the_windows_only_where_the_frames_hold_lookalikes(sim_run, caplog):
    """fuse.association.other_vehicle_lookalikes_per_mpx: a number as it is; auto: none for
    the landmark-mode simulation (its descriptors are distinct by construction), and for one
    vehicle (no other's landmarks to look for), without reading the frames."""
    cfg, inputs, _ = _inputs(sim_run, "fuse.association.other_vehicle_lookalikes_per_mpx=5")
    assert stage.lookalikes_per_mpx(cfg.fuse, inputs) == 5.0
    cfg, inputs, _ = _inputs(sim_run)
    with caplog.at_level("INFO", logger="cvslam.fuse"):
        assert stage.lookalikes_per_mpx(cfg.fuse, inputs) == 0.0
    assert "0.0 % of" in caplog.text and "no bound on the windows" in caplog.text
    assert stage.lookalikes_per_mpx(cfg.fuse, inputs[:1]) == 0.0
    assert stage.settings_for(cfg.fuse, "hinf", inputs).other_vehicle_lookalike_bound == np.inf


def test_a_diverging_filter_is_reported_with_its_time(sim_run, tmp_path, cvslam):
    run = _copy(sim_run, tmp_path)
    # claim 100x more precise pixels than the simulator's: NIS explodes (with the map's
    # check of the pose on, the vehicle is declared lost first and the run goes on)
    r = cvslam("fuse", run, "--set", "fuse.association.pixel_sigma_px=0.005",
               "--set", "fuse.association.gate_probability=0.999999999",
               "--set", "fuse.relocalisation.enabled=false")  # fmt: skip
    assert r.code == 1
    assert "diverged" in r.err and "s into the run" in r.err and "NIS" in r.err
    # besides the lines saying what "auto" chose (motion model, landmark coordinates, the
    # observability constraint, the bearing noise by octave, the landmarks a frame, the
    # look-alikes)
    chose = ("model", "coordinates", "constraint", "octave", "updated a frame", "look-alike")
    said = [ln for ln in r.err.strip().splitlines() if not any(w in ln for w in chose)]
    assert len(said) == 1 and said[0].startswith("cvslam: error:")
    assert not (run / "fuse").exists() and not (run / "fuse.partial").exists()


def test_an_interrupted_fuse_leaves_no_complete_looking_output(sim_run, tmp_path, monkeypatch):
    run = _copy(sim_run, tmp_path)
    old = run / "fuse"
    old.mkdir()
    (old / "uav1.tum").write_text("previous run\n")

    def interrupted(path: Path, *args: object, **kwargs: object) -> None:
        path.write_bytes(b"half a log")  # the last file of the folder, cut short
        raise KeyboardInterrupt

    monkeypatch.setattr(stage, "write_result_mcap", interrupted)
    with pytest.raises(KeyboardInterrupt):
        stage.run(load_config((), list(NOISE[1::2])), run)
    assert sorted(p.name for p in old.iterdir()) == ["uav1.tum"]  # the old folder, untouched
    assert (old / "uav1.tum").read_text() == "previous run\n"
    assert not list(run.glob("*.partial"))
    assert "fuse" not in RunDir(run).load().get("stages", {})  # not recorded as done


def test_bad_inputs_give_one_line_errors(sim_run, tmp_path, cvslam):
    run = _copy(sim_run, tmp_path)
    # no motion data and the constant-velocity fallback turned off
    r = cvslam("fuse", run, "--set", "logs.vehicle_defaults.topics.imu=/nothing",
               "--set", "fuse.motion.fallback_constant_velocity=false")  # fmt: skip
    assert r.code == 1 and "no IMU or odometry" in r.err and "constant_velocity" in r.err
    # ... by default it runs, with the constant-velocity model, and says so in one line
    r = cvslam("fuse", run, "--force", "--set", "logs.vehicle_defaults.topics.imu=/nothing",
               "--set", "fuse.divergence.nis_per_dof_max=1000")  # fmt: skip
    assert r.code == 0, r.err
    said = [ln for ln in r.err.splitlines() if "motion model" in ln]
    assert said == [
        f"cvslam: {v}: motion model constant_velocity (no IMU or odometry in the logs; "
        "fuse.motion.model to choose)"
        for v in ("uav1", "uav2")
    ]
    # a feature file of another format version
    f = run / "features" / "uav1.npz"
    with np.load(f) as npz:
        data = {k: npz[k] for k in npz.files}
    data["version"] = np.array(99)
    np.savez(f, **data)
    r = cvslam("fuse", run, "--force")
    assert r.code == 1 and "version 99" in r.err and "uav1.npz" in r.err
    # no features at all
    r = cvslam("fuse", tmp_path / "empty")
    assert r.code == 1 and "no feature files" in r.err


def test_the_initial_velocity_is_the_trajectorys_at_its_first_pose():
    """A turn sampled at 10 Hz from its first pose: the velocity and turn rate there are
    the truth's (the parabola through three samples), not the forward difference's half a
    sample later."""
    t_s = np.arange(6) * 0.1
    v0, a = np.array([11.0, 0.0, -0.5]), np.array([0.0, 2.5, 0.2])
    p = np.array([1.0, 2.0, -100.0]) + np.outer(t_s, v0) + 0.5 * np.outer(t_s**2, a)
    yaw = 0.3 + 0.25 * t_s + 0.5 * 0.4 * t_s**2  # a turn rate of 0.25 rad/s, growing
    q = np.array([[0.0, 0.0, np.sin(y / 2), np.cos(y / 2)] for y in yaw])  # xyzw about down
    stamps_ns = (t_s * 1e9).astype(np.int64) + 5_000_000_000
    gt = PoseTable(stamps_ns, p, q)
    cfg = load_config().fuse
    for i, first_ns in ((0, stamps_ns[0]), (2, stamps_ns[2])):
        start_ns, p0, euler, v_nav, w_body = stage._initial_pose(cfg, "uav1", gt, first_ns, 0)
        assert start_ns == stamps_ns[i]
        np.testing.assert_allclose(p0, p[i])
        np.testing.assert_allclose(euler, [0.0, 0.0, yaw[i]], atol=1e-12)
        np.testing.assert_allclose(v_nav, v0 + a * t_s[i], atol=1e-9)
        np.testing.assert_allclose(w_body, [0.0, 0.0, 0.25 + 0.4 * t_s[i]], atol=1e-9)
    forward = (p[1] - p[0]) / 0.1
    assert abs(forward[1] - v0[1]) > 0.1  # what the first pose had before
    np.testing.assert_allclose(stage._derivative_at(stamps_ns[:2], p[:2], stamps_ns[0]), forward)
    np.testing.assert_allclose(stage._derivative_at(stamps_ns[:1], p[:1], stamps_ns[0]), 0.0)
