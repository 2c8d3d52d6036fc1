"""Reading logs into per-vehicle records: pairing, ordering, calibration, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import CalibrationError, LogError
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.records.log import ImuSample, PoseRecord, StereoFrame
from tests.synth import write_stereo_log


def _logset(*paths, overrides=(), strict=True):
    return LogSet(
        [McapLogSource(p) for p in paths], load_config(overrides=overrides).logs, strict=strict
    )


def test_records_round_trip_images_imu_and_ground_truth(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=8)
    logs = _logset(synth.path)
    assert list(logs.vehicles) == ["uav1"]
    recs = list(logs.records())
    frames = [r for r in recs if isinstance(r, StereoFrame)]
    imu = [r for r in recs if isinstance(r, ImuSample)]
    gt = [r for r in recs if isinstance(r, PoseRecord)]
    assert len(frames) == 8 and len(imu) == len(synth.imu) and len(gt) == 8
    for f, (ls, limg), (rs, rimg) in zip(frames, synth.left, synth.right, strict=True):
        assert f.stamp_ns == ls and f.right.stamp_ns == rs
        np.testing.assert_array_equal(f.left.image, limg)
        np.testing.assert_array_equal(f.right.image, rimg)
    for s, (stamp, gyro, acc) in zip(imu, synth.imu, strict=True):
        assert s.stamp_ns == stamp
        np.testing.assert_array_equal(s.gyro_rad_s, gyro)
        np.testing.assert_array_equal(s.accel_m_s2, acc)
    stamps = [r.stamp_ns for r in recs]
    assert stamps == sorted(stamps)
    assert logs.stats["uav1"].stereo_pairs == 8


def test_pairing_within_tolerance_and_unpaired_counts(tmp_path):
    synth = write_stereo_log(
        tmp_path / "a.mcap", n_frames=10, right_offset_ns=1_500_000, drop_right=(3, 7)
    )
    logs = _logset(synth.path)
    frames = [r for r in logs.records() if isinstance(r, StereoFrame)]
    assert len(frames) == 8
    assert all(f.pair_offset_ns == 1_500_000 for f in frames)
    st = logs.stats["uav1"]
    assert (st.stereo_pairs, st.unpaired_left, st.unpaired_right) == (8, 2, 0)
    # a tighter tolerance than the offset pairs nothing
    tight = _logset(synth.path, overrides=["logs.stereo_pair_tolerance_ms=1.0"])
    assert not [r for r in tight.records() if isinstance(r, StereoFrame)]
    assert tight.stats["uav1"].unpaired_left == 10
    assert tight.stats["uav1"].unpaired_right == 8


def test_two_logs_two_vehicles_merge_in_time_order(tmp_path):
    a = write_stereo_log(tmp_path / "a.mcap", vehicle="uav1", n_frames=5, seed=1)
    b = write_stereo_log(
        tmp_path / "b.mcap", vehicle="uav2", n_frames=5, seed=2, t0_ns=1_025_000_000
    )
    logs = _logset(a.path, b.path)
    assert sorted(logs.vehicles) == ["uav1", "uav2"]
    recs = list(logs.records())
    stamps = [r.stamp_ns for r in recs]
    assert stamps == sorted(stamps)
    assert {r.vehicle for r in recs} == {"uav1", "uav2"}
    only2 = list(logs.records(vehicles=["uav2"]))
    assert only2 and all(r.vehicle == "uav2" for r in only2)
    with pytest.raises(LogError, match="no vehicle 'uav3'"):
        list(logs.records(vehicles=["uav3"]))


def test_nan_imu_dropped_and_counted_backwards_reported(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=4, nan_imu=(3, 9), backwards_imu_at=20)
    logs = _logset(synth.path)
    imu = [r for r in logs.records() if isinstance(r, ImuSample)]
    assert len(imu) == len(synth.imu)
    assert all(np.all(np.isfinite(s.gyro_rad_s)) for s in imu)
    ts = logs.stats["uav1"].topics["/uav1/imu"]
    assert ts.dropped_nonfinite == 2
    assert ts.backwards == 1
    assert any("backwards" in p.text for p in logs.problems)


def test_calibration_from_camera_info_and_tf_static(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", baseline_m=0.25)
    rig = _logset(synth.path).rig("uav1")
    assert rig.left.source.startswith("CameraInfo") and "/tf_static" in rig.left.source
    assert rig.baseline_m == pytest.approx(0.25)
    assert rig.baseline_from_projection_m == pytest.approx(0.25)
    assert rig.rectified


def test_calibration_from_projection_when_no_tf(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", baseline_m=0.3, tf=False)
    rig = _logset(synth.path).rig("uav1")
    assert rig.baseline_m == pytest.approx(0.3)


def test_calibration_from_rig_config_when_no_camera_info(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", camera_info=False, tf=False)
    with pytest.raises(CalibrationError, match="no calibration for the left camera"):
        _logset(synth.path).rig("uav1")
    base = "logs.vehicles.uav1.rig"
    cam = "{width: 64, height: 48, fx: 50, fy: 50, cx: 32, cy: 24}"
    right_T = "[1,0,0,0.12, 0,1,0,0, 0,0,1,0, 0,0,0,1]"
    logs = _logset(
        synth.path,
        overrides=[
            f"{base}.left={cam}",
            f"{base}.right={cam}",
            f"{base}.right.T_body_cam={right_T}",
        ],
    )
    rig = logs.rig("uav1")
    assert rig.left.source.startswith("config")
    assert rig.baseline_m == pytest.approx(0.12)
    assert len([r for r in logs.records() if isinstance(r, StereoFrame)]) == 10


def test_zero_baseline_and_bad_focal_length_rejected(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", camera_info=False, tf=False)
    base = "logs.vehicles.uav1.rig"
    cam = "{width: 64, height: 48, fx: 50, fy: 50, cx: 32, cy: 24}"
    logs = _logset(synth.path, overrides=[f"{base}.left={cam}", f"{base}.right={cam}"])
    with pytest.raises(CalibrationError, match="zero stereo baseline"):
        logs.rig("uav1")
    bad = "{width: 64, height: 48, fx: -5, fy: 50, cx: 32, cy: 24}"
    logs = _logset(synth.path, overrides=[f"{base}.left={bad}", f"{base}.right={cam}"])
    with pytest.raises(CalibrationError, match="non-positive focal length"):
        logs.rig("uav1")


def test_image_size_disagreeing_with_calibration(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", size=(64, 48), info_size=(80, 48))
    with pytest.raises(LogError, match=r"image is 64x48 but its calibration .* is for 80x48"):
        list(_logset(synth.path).records())
    lenient = _logset(synth.path, strict=False)
    list(lenient.records())
    assert any(p.severity == "error" and "64x48" in p.text for p in lenient.problems)


def test_configured_topic_absent_is_an_error(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap")
    with pytest.raises(LogError, match=r"topic /uav1/imu_typo .*is not in the log"):
        _logset(synth.path, overrides=["logs.vehicles.uav1.topics.imu=/uav1/imu_typo"])
    with pytest.raises(LogError, match="none of vehicle ghost's topics"):
        _logset(synth.path, overrides=["logs.vehicles.ghost.kind=uav"])


def test_memory_is_bounded_by_window_not_length(tmp_path):
    """The reorder heap and pair queues never hold more than a window's worth of data."""
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=60)
    logs = _logset(synth.path)
    n = sum(1 for _ in logs.records())
    # 100 ms window at 200 Hz IMU + 2 x 20 Hz images + 20 Hz gt is ~ 20 + 4 + 2 records
    assert n > 600
    assert 10 < logs.peak_buffered < 40
