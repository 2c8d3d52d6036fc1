"""The command line: help everywhere, the error boundary, `cvslam info`."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from cvslam_cli import __version__
from cvslam_cli.cli import cli
from cvslam_cli.io.mcap_writer import LogWriter, header
from tests.scenarios import small_uav_scenario
from tests.synth import camera, write_stereo_log


def _commands(group, prefix=()):
    for name, cmd in group.commands.items():
        yield (*prefix, name)
        if hasattr(cmd, "commands"):
            yield from _commands(cmd, (*prefix, name))


def test_help_on_every_command_and_version(cvslam):
    paths = list(_commands(cli))
    assert ("info",) in paths and ("import", "euroc") in paths and ("import", "kitti") in paths
    for path in paths:
        res = cvslam(*path, "--help")
        assert res.code == 0 and "Usage:" in res.out, path
    res = cvslam("--version")
    assert res.code == 0 and __version__ in res.out


def test_stage_commands_take_config_and_set(cvslam):
    for path in [("info",), ("import", "euroc"), ("import", "kitti")]:
        out = cvslam(*path, "--help").out
        assert "--config FILE" in out and "--set KEY.PATH=VALUE" in out, path


def test_info_reports_vehicle_topics_pairs_and_calibration(cvslam, tmp_path):
    synth = write_stereo_log(
        tmp_path / "a.mcap", n_frames=12, drop_right=(5,), nan_imu=(7,), baseline_m=0.2
    )
    res = cvslam("info", synth.path)
    assert res.code == 0, res.err
    assert "vehicle uav1" in res.out
    assert "stereo pairs: 11 (unpaired left 1, right 0" in res.out
    assert "baseline 0.2000 m" in res.out
    assert "image 64x48 mono8" in res.out
    assert "1 message(s) with NaN/inf values dropped" in res.out
    res = cvslam("info", "--json", synth.path)
    report = json.loads(res.out)
    v = report["vehicles"]["uav1"]
    topics = {t["role"]: t for t in v["topics"]}
    assert topics["imu"]["rate_hz"] == pytest.approx(200.0)
    assert topics["left_image"]["rate_hz"] == pytest.approx(20.0)
    assert topics["left_image"]["count"] == 12 and topics["right_image"]["count"] == 11
    assert topics["imu"]["dropped_nonfinite"] == 1
    assert v["stereo"]["pairs"] == 11
    assert v["calibration"]["left"]["fx"] == 50.0
    assert v["calibration"]["baseline_m"] == pytest.approx(0.2)
    assert v["duration_s"] == pytest.approx(0.595, abs=0.01)


def test_info_reports_gaps(cvslam, tmp_path):
    path = tmp_path / "gap.mcap"
    with LogWriter(path) as log:
        for k, t in enumerate([0, 10, 20, 30, 100, 110, 120]):
            log.write_imu("/v/imu", 10**9 + t * 1_000_000, np.zeros(3), np.zeros(3), "v")
            del k
    report = json.loads(cvslam("info", "--json", path).out)
    imu = report["vehicles"]["v"]["topics"][0]
    assert imu["gaps"] == 1 and imu["largest_gap_s"] == pytest.approx(0.07)
    assert any("gap" in p["text"] for p in report["problems"])


def _write_odd_encoding(path):
    with LogWriter(path) as log:
        for side in ("left", "right"):
            cam = camera(2, 2, 2.0, right=side == "right", frame_id=f"v/{side}")
            log.write_camera_info(f"/v/stereo/{side}/camera_info", 10**9, cam)
            log.write(
                f"/v/stereo/{side}/image_raw",
                "sensor_msgs/msg/Image",
                {
                    "header": header(10**9, f"v/{side}"),
                    "height": 2,
                    "width": 2,
                    "encoding": "nv21",
                    "is_bigendian": 0,
                    "step": 4,
                    "data": bytes(8),
                },
                10**9,
            )


@pytest.mark.parametrize(
    "case, expected",
    [
        ("missing", "nope.mcap: file not found"),
        ("not_mcap", "not an MCAP file"),
        ("absent_topic", "topic /v9/imu (logs.vehicles.uav1.topics.imu) is not in the log"),
        (
            "size",
            "image is 64x48 but its calibration (CameraInfo /uav1/stereo/left/camera_info "
            "+ /tf_static) is for 70x48",
        ),
        ("encoding", "unknown image encoding 'nv21'"),
        ("zero_focal", "non-positive focal length"),
        ("bad_key", "--set logs.nope=1: logs.nope: unknown key"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(cvslam, tmp_path, case, expected):
    args: list[object] = ["info"]
    if case == "missing":
        args.append(tmp_path / "nope.mcap")
    elif case == "not_mcap":
        p = tmp_path / "x.mcap"
        p.write_text("hello")
        args.append(p)
    elif case == "absent_topic":
        args += [
            write_stereo_log(tmp_path / "a.mcap").path,
            "--set",
            "logs.vehicles.uav1.topics.imu=/v9/imu",
        ]
    elif case == "size":
        args.append(write_stereo_log(tmp_path / "a.mcap", info_size=(70, 48)).path)
    elif case == "encoding":
        _write_odd_encoding(tmp_path / "e.mcap")
        args.append(tmp_path / "e.mcap")
    elif case == "zero_focal":
        args.append(write_stereo_log(tmp_path / "a.mcap", fx=0.0).path)
    elif case == "bad_key":
        args += [write_stereo_log(tmp_path / "a.mcap").path, "--set", "logs.nope=1"]
    res = cvslam(*args)
    assert res.code == 1
    errors = [ln for ln in res.err.splitlines() if ln.startswith("cvslam: error:")]
    assert len(errors) == 1 and expected in errors[0], res.err
    assert "Traceback" not in res.err


def test_usage_error_exits_2(cvslam):
    assert cvslam("info").code == 2
    assert cvslam("frobnicate").code == 2


def test_console_script_error_has_no_traceback(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\0" * 100)
    proc = subprocess.run(
        [sys.executable, "-m", "cvslam_cli", "info", str(bad)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 1
    assert proc.stderr.strip() == f"cvslam: error: {bad}: not an MCAP file (bad magic bytes)"


def test_truncated_log_warns_and_reports_readable_prefix(cvslam, tmp_path):
    synth = write_stereo_log(
        tmp_path / "full.mcap", n_frames=30, size=(160, 120), chunk_size=64 * 1024
    )
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(synth.path.read_bytes()[: synth.path.stat().st_size // 2])
    res = cvslam("info", "--json", cut)
    assert res.code == 0, res.err
    warnings = [ln for ln in res.err.splitlines() if ln.startswith("cvslam: warning:")]
    assert any("truncated" in w and "lost the messages logged" in w for w in warnings)
    report = json.loads(res.out)
    assert 5 < report["vehicles"]["uav1"]["stereo"]["pairs"] < 30
    assert any("truncated" in p["text"] for p in report["problems"])


def test_backwards_stamps_and_nan_are_reported_not_fatal(cvslam, tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", backwards_imu_at=30, nan_imu=(2,))
    res = cvslam("info", synth.path)
    assert res.code == 0
    assert "/uav1/imu: timestamps go backwards 1 time(s)" in res.out
    assert "/uav1/imu: 1 message(s) with NaN/inf values dropped" in res.out


def test_zero_baseline_is_fatal(cvslam, tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", camera_info=False, tf=False)
    cam = "{width: 64, height: 48, fx: 50, fy: 50, cx: 32, cy: 24}"
    res = cvslam(
        "info",
        synth.path,
        "--set",
        f"logs.vehicles.uav1.rig.left={cam}",
        "--set",
        f"logs.vehicles.uav1.rig.right={cam}",
    )
    assert res.code == 1
    last = res.err.splitlines()[-1]
    assert "no stereo extrinsics (zero baseline): /tf_static does not link uav1/base_link" in last
    assert "logs.vehicles.uav1.rig.left.T_body_cam and rig.right.T_body_cam" in last


def test_import_euroc_then_info(cvslam, shared_data, tmp_path):
    out = tmp_path / "euroc.mcap"
    res = cvslam(
        "import", "euroc", shared_data / "euroc_v101_micro" / "mav0", "-o", out, "--vehicle", "uav1"
    )
    assert res.code == 0, res.err
    assert (tmp_path / "euroc.config.yaml").is_file()  # the resolved config beside the output
    report = json.loads(cvslam("info", "--json", out).out)
    v = report["vehicles"]["uav1"]
    topics = {t["role"]: t for t in v["topics"]}
    assert v["stereo"]["pairs"] == 95
    assert topics["left_image"]["rate_hz"] == pytest.approx(20.0, rel=1e-3)
    assert topics["imu"]["rate_hz"] == pytest.approx(200.0, rel=0.01)
    assert topics["left_image"]["image"] == {"width": 752, "height": 480, "encoding": "mono8"}
    assert v["calibration"]["rectified"] is False
    assert v["calibration"]["left"]["distortion_model"] == "plumb_bob"
    assert report["problems"] == []
    md = report["logs"][0]["metadata"]["cvslam.import"]
    assert md["nav_frame"] == "NED" and md["dataset"] == "euroc"
    # another tool (rosbags) opens the imported log with its standard ROS 2 schemas
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        conn = next(c for c in reader.connections if c.topic == "/uav1/stereo/left/image_raw")
        _, _, raw = next(iter(reader.messages(connections=[conn])))
        first = reader.deserialize(raw, conn.msgtype)
    assert counts["/uav1/stereo/left/image_raw"] == 95 and counts["/uav1/imu"] == 1141
    png = sorted((shared_data / "euroc_v101_micro/mav0/cam0/data").glob("*.png"))[0]
    expected = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(np.asarray(first.data).reshape(480, 752), expected)


def test_import_kitti_then_info(cvslam, shared_data, tmp_path):
    out = tmp_path / "kitti.mcap"
    res = cvslam("import", "kitti", shared_data / "kitti_clip_a", "-o", out, "--vehicle", "car1")
    assert res.code == 0, res.err
    text = cvslam("info", out).out
    assert "stereo pairs: 51 (unpaired left 0, right 0" in text
    assert "baseline 0.5372 m, rectified" in text
    report = json.loads(cvslam("info", "--json", out).out)
    topics = {t["role"]: t for t in report["vehicles"]["car1"]["topics"]}
    assert topics["left_image"]["rate_hz"] == pytest.approx(10.0)
    assert report["vehicles"]["car1"]["calibration"]["baseline_m"] == pytest.approx(0.537, abs=1e-3)


def test_import_bad_folder_is_one_line(cvslam, tmp_path):
    res = cvslam("import", "kitti", tmp_path / "nowhere", "-o", tmp_path / "k.mcap")
    assert res.code == 1 and "Traceback" not in res.err
    assert len(res.err.strip().splitlines()) == 1 and "nowhere" in res.err
    assert not list(tmp_path.glob("k.*"))


def test_simulate_command(cvslam, tmp_path):
    scenario = small_uav_scenario(tmp_path)
    out = tmp_path / "sim"
    res = cvslam(
        "simulate", scenario, "-o", out, "--set", "mode=landmarks", "--seed", "5", "--duration", "3"
    )
    assert res.code == 0, res.err
    assert "uav1:" in res.err and "landmark observations" in res.err
    assert (out / "features" / "uav1.npz").is_file()
    text = cvslam("info", out / "uav1.mcap", out / "uav2.mcap").out
    assert "vehicle uav1" in text and "vehicle uav2" in text
    res = cvslam("simulate", scenario, "-o", out, "--set", "mode=landmarks")
    assert res.code == 1 and "already exists" in res.err and "--force" in res.err
    res = cvslam("simulate", scenario, "-o", tmp_path / "x", "--set", "vehicles.uav1.speed=3")
    assert res.code == 1
    assert res.err.strip().endswith(
        "vehicles.uav1.speed: unknown key (expected one of: kind, "
        "waypoints_nav_m, closed, speed_m_s, start_s, imu_rate_hz, "
        "imu, odometry_rate_hz, odometry, camera, ground_truth_at)"
    )
    res = cvslam("simulate", tmp_path / "missing.yaml", "-o", tmp_path / "y")
    assert res.code == 1 and "missing.yaml: not found, expected a scenario file" in res.err


def test_extract_command(cvslam, tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=4, size=(160, 120), fx=120.0)
    run_dir = tmp_path / "run"
    res = cvslam("extract", synth.path, "-o", run_dir, "--workers", "1")
    assert res.code == 0, res.err
    assert "uav1: 4 stereo frames" in res.err
    assert (run_dir / "features" / "uav1.npz").is_file()
    assert (run_dir / "features" / "extract.config.yaml").is_file()
    assert "up to date" in cvslam("extract", synth.path, "-o", run_dir).err
    res = cvslam("extract", synth.path, "-o", run_dir, "--set", "extract.sift.sigma=2.0")
    assert res.code == 1 and "different config (extract.sift.sigma: 1.6 -> 2.0)" in res.err
    res = cvslam(
        "extract",
        synth.path,
        "-o",
        run_dir,
        "--set",
        "extract.sift.sigma=2.0",
        "--force",
        "--workers",
        "1",
    )
    assert res.code == 0
    res = cvslam(
        "extract", synth.path, "-o", tmp_path / "r2", "--set", "extract.stereo.dist_ratio=1.5"
    )
    assert res.code == 1
    assert "extract.stereo.dist_ratio: expected a number > 0.0 and <= 1.0, got 1.5" in res.err
