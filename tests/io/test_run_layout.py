"""The run directory's layout: the names of DESIGN.md section 5 and how inputs are found."""

from __future__ import annotations

from pathlib import Path

import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.run_layout import (
    FUSE,
    FUSE_EKF,
    FUSE_EKF_SINGLE,
    FUSE_SINGLE,
    MERGED_MOSAIC,
    FuseFolder,
    RunLayout,
    SimLayout,
    fuse_name,
    mosaic_name,
    resolved_config_beside,
)


def touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("x")
    return path


def test_folder_names_of_every_stage(tmp_path):
    assert [FUSE, FUSE_SINGLE, FUSE_EKF, FUSE_EKF_SINGLE] == [
        "fuse", "fuse_single", "fuse_ekf", "fuse_ekf_single"
    ]  # fmt: skip
    assert fuse_name("ekf", single=True) == FUSE_EKF_SINGLE
    assert [mosaic_name(s) for s in ("fused", "deadreckoning", "groundtruth")] == [
        "mosaic", "mosaic_deadreckoning", "mosaic_groundtruth"
    ]  # fmt: skip
    run = RunLayout(tmp_path)
    assert run.run_file == tmp_path / "run.yaml"
    assert run.feature_file("uav1") == tmp_path / "features" / "uav1.npz"
    assert run.feature_stats("uav1") == tmp_path / "features" / "uav1_stats.csv"
    assert run.extract_config == tmp_path / "features" / "extract.config.yaml"
    assert run.fuse().path == tmp_path / "fuse" and run.fuse(FUSE_EKF).name == "fuse_ekf"
    assert run.diverged_timeline(FUSE_EKF) == tmp_path / "fuse_ekf_diverged_timeline.csv"
    assert run.mosaic().path == tmp_path / "mosaic"
    assert run.eval.path == tmp_path / "eval"
    assert resolved_config_beside(tmp_path / "k.mcap") == tmp_path / "k.config.yaml"


def test_files_of_each_folder(tmp_path):
    fuse = FuseFolder(tmp_path)
    got = [
        fuse.trajectory("uav1"),
        fuse.trajectory("uav1", deadreckoning=True),
        fuse.pose_covariances("uav1"),
        fuse.map_csv,
        fuse.map_ply,
        fuse.timeline,
        fuse.events,
        fuse.result_mcap,
        fuse.resolved_config,
    ]
    assert [p.name for p in got] == [
        "uav1.tum", "uav1_deadreckoning.tum", "uav1_pose_cov.npz", "map.csv", "map.ply",
        "timeline.csv", "events.csv", "result.mcap", "fuse.config.yaml",
    ]  # fmt: skip
    assert all(p.parent == tmp_path for p in got)
    mosaic = RunLayout(tmp_path).mosaic()
    assert [p.name for p in (mosaic.image("all"), mosaic.world_file("all"))] == [
        "all.png", "all.pgw"
    ]  # fmt: skip
    assert mosaic.overlay(MERGED_MOSAIC).name == "all_overlay.png"
    ev = RunLayout(tmp_path).eval
    assert [p.name for p in (ev.metrics_json, ev.metrics_csv, ev.headline_csv, ev.report_html)] == [
        "metrics.json", "metrics.csv", "headline.csv", "report.html"
    ]  # fmt: skip
    assert ev.figure("nees") == tmp_path / "eval" / "figures" / "nees.png"


def test_a_simulator_output_is_a_run_directory(tmp_path):
    sim = SimLayout(tmp_path)
    assert sim.feature_file("uav1") == RunLayout(tmp_path).feature_file("uav1")
    assert sim.log("uav1") == tmp_path / "uav1.mcap"
    assert sim.scenario == tmp_path / "scenario.yaml"
    truth = [sim.true_trajectory("u"), sim.true_imu_biases("u"), sim.true_depth("u")]
    assert [p.name for p in truth] == ["u.tum", "u_imu.npz", "u_depth.npz"]
    assert sim.world == tmp_path / "truth" / "world.npz"
    assert sim.true_landmarks == tmp_path / "truth" / "landmarks.csv"


def test_fuse_folder_vehicles_and_data_files(tmp_path):
    fuse = RunLayout(tmp_path).fuse()
    assert not fuse.has_trajectories()
    for name in ("uav2.tum", "uav1.tum", "uav1_deadreckoning.tum", "uav1_pose_cov.npz",
                 "map.csv", "map.ply", "result.mcap"):  # fmt: skip
        touch(fuse.path / name)
    assert fuse.has_trajectories()
    assert fuse.vehicles() == ["uav1", "uav2"]
    assert sorted(p.name for p in fuse.data_files()) == [
        "map.csv", "uav1.tum", "uav1_deadreckoning.tum", "uav1_pose_cov.npz", "uav2.tum"
    ]  # fmt: skip
    assert fuse.trajectories(["uav1"], deadreckoning=True) == {
        "uav1": fuse.path / "uav1_deadreckoning.tum"
    }
    with pytest.raises(CvslamError, match=r"uav2_deadreckoning.tum: trajectory not found"):
        fuse.trajectories(["uav1", "uav2"], deadreckoning=True)


def test_mosaic_pngs(tmp_path):
    mosaic = RunLayout(tmp_path).mosaic()
    assert mosaic.pngs() == []
    for name in ("uav1.png", "all.png", "all.pgw", "all_overlay.png"):
        touch(mosaic.path / name)
    assert [p.name for p in mosaic.pngs()] == ["all.png", "all_overlay.png", "uav1.png"]


def test_feature_files_sorted_or_an_error_with_the_remedy(tmp_path):
    run = RunLayout(tmp_path)
    with pytest.raises(CvslamError, match=r"features: no feature files .*; run this first$"):
        run.feature_files("run this first")
    for v in ("uav2", "uav1"):
        touch(run.feature_file(v))
    touch(run.feature_stats("uav1"))
    assert run.feature_files("-") == [run.feature_file("uav1"), run.feature_file("uav2")]


def test_logs_from_the_features_metadata_else_beside(tmp_path):
    run = RunLayout(tmp_path / "run")
    log_b, log_a = touch(tmp_path / "b.mcap"), touch(tmp_path / "a.mcap")
    metas = [
        {"inputs": [{"path": str(log_b)}, {"path": str(log_a)}]},
        {"inputs": [{"path": str(log_b)}]},
    ]
    assert run.find_logs(metas) == [log_b, log_a]  # recorded order, once each
    with pytest.raises(CvslamError, match=r"gone.mcap: log recorded .* not found; give the"):
        run.find_logs([{"inputs": [{"path": str(tmp_path / "gone.mcap")}]}])
    sim = SimLayout(tmp_path)  # a simulator output: no recorded inputs, logs beside
    assert sim.find_logs([{}, {}]) == [log_a, log_b]
    assert RunLayout(tmp_path / "empty").find_logs([]) == []


def test_fuse_folders_and_export_dirs(tmp_path):
    layout = RunLayout(tmp_path)
    assert layout.fuse_folders() == []
    for name in ("fuse_single", "fuse"):
        touch(layout.fuse(name).path / "uav1.tum")
    (tmp_path / "fuse_ekf").mkdir()  # no trajectories: not listed
    touch(layout.diverged_timeline("fuse_ekf"))
    assert [f.name for f in layout.fuse_folders()] == ["fuse", "fuse_single"]
    assert layout.export_dir("fuse_single", "enu") == tmp_path / "export" / "fuse_single_enu"
