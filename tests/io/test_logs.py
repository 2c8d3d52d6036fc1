"""`LogSet`, the facade: logs in, per-vehicle records out, in stamp order, bounded memory;
calibration resolved before the images stream and checked against them."""

from __future__ import annotations

from collections.abc import Collection, Iterator

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import LogError
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource, RawMessage, TopicInfo
from cvslam_cli.records.log import ImuSample, PoseRecord, StereoFrame
from tests.synth import write_stereo_log


def _logset(*paths, overrides=(), strict=True):
    return LogSet(
        [McapLogSource(p) for p in paths], load_config(overrides=overrides).logs, strict=strict
    )


class _CountingSource:
    """An MCAP source that records the topics of every `messages` call."""

    def __init__(self, src: McapLogSource) -> None:
        self.src, self.name, self.warnings = src, src.name, src.warnings
        self.calls: list[set[str]] = []

    def topics(self) -> dict[str, TopicInfo]:
        return self.src.topics()

    def messages(self, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
        self.calls.append(set(topics or ()))
        return self.src.messages(topics)


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


def test_calibration_is_read_before_the_images_stream_and_once(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=4)
    src = _CountingSource(McapLogSource(synth.path))
    logs = LogSet([src], load_config().logs)
    assert len([r for r in logs.records() if isinstance(r, StereoFrame)]) == 4
    info = {"/uav1/stereo/left/camera_info", "/uav1/stereo/right/camera_info"}
    *before, stream = src.calls
    assert "/uav1/stereo/left/image_raw" in stream and not stream & info
    assert {t for c in before for t in c} == info | {"/tf_static"}
    n = len(src.calls)
    list(logs.records())
    assert len(src.calls) == n + 1  # the second stream only
    # without images no calibration is needed
    fresh = _CountingSource(McapLogSource(synth.path))
    assert list(LogSet([fresh], load_config().logs).records(roles=("imu",)))
    assert fresh.calls == [{"/uav1/imu"}]


def test_image_size_disagreeing_with_calibration(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", size=(64, 48), info_size=(80, 48))
    with pytest.raises(LogError, match=r"image is 64x48 but its calibration .* is for 80x48"):
        list(_logset(synth.path).records())
    lenient = _logset(synth.path, strict=False)
    list(lenient.records())
    assert any(p.severity == "error" and "64x48" in p.text for p in lenient.problems)


def test_missing_calibration_is_an_error_at_the_first_image(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=3, camera_info=False, tf=False)
    with pytest.raises(LogError, match="no calibration for the left camera"):
        list(_logset(synth.path).records())
    assert list(_logset(synth.path).records(roles=("imu",)))  # no images: not needed
    lenient = _logset(synth.path, strict=False)
    frames = [r for r in lenient.records() if isinstance(r, StereoFrame)]
    assert len(frames) == 3
    errors = [p.text for p in lenient.problems if p.severity == "error"]
    assert len(errors) == 1 and "no calibration for the left camera" in errors[0]


def test_memory_is_bounded_by_window_not_length(tmp_path):
    """The reorder heap and pair queues never hold more than a window's worth of data."""
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=60)
    logs = _logset(synth.path)
    n = sum(1 for _ in logs.records())
    # 100 ms window at 200 Hz IMU + 2 x 20 Hz images + 20 Hz gt is ~ 20 + 4 + 2 records
    assert n > 600
    assert 10 < logs.peak_buffered < 40
