"""Per-topic statistics and the problems list."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import LogError
from cvslam_cli.io.log_stats import Problem, Problems, TopicStats, VehicleStats
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.records.log import ImuSample
from tests.synth import write_stereo_log


def test_nan_imu_dropped_and_counted_backwards_reported(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=4, nan_imu=(3, 9), backwards_imu_at=20)
    logs = LogSet([McapLogSource(synth.path)], load_config().logs)
    imu = [r for r in logs.records() if isinstance(r, ImuSample)]
    assert len(imu) == len(synth.imu)
    assert all(np.all(np.isfinite(s.gyro_rad_s)) for s in imu)
    ts = logs.stats["uav1"].topics["/uav1/imu"]
    assert ts.dropped_nonfinite == 2
    assert ts.backwards == 1
    assert any("backwards" in p.text for p in logs.problems)


def test_topic_stats_rate_span_gaps_and_backwards():
    ts = TopicStats("/imu", "imu", "sensor_msgs/msg/Imu")
    stamps = [0, 10, 20, 30, 80, 90, 85, 100]  # a 50 ns gap, then 85 goes backwards
    ok = [ts.observe(s) for s in stamps]
    assert ok == [True] * 6 + [False, True]
    assert (ts.count, ts.backwards, ts.first_ns, ts.last_ns) == (8, 1, 0, 100)
    assert ts.nominal_period_ns == 10.0 and ts.rate_hz == pytest.approx(1e8)
    assert ts.span_s == pytest.approx(100e-9)
    assert ts.gaps(3.0) == [pytest.approx(50e-9)] and ts.gaps(6.0) == []
    empty = TopicStats("/x", "imu", "sensor_msgs/msg/Imu")
    assert (empty.rate_hz, empty.span_s, empty.gaps(3.0)) == (0.0, 0.0, [])


def test_vehicle_stats_create_a_topic_at_its_first_message():
    vs = VehicleStats()
    ts = vs.topic("/imu", "imu", "sensor_msgs/msg/Imu")
    assert vs.topic("/imu", "imu", "sensor_msgs/msg/Imu") is ts and list(vs.topics) == ["/imu"]


def test_problems_listed_once_errors_raise_when_strict(caplog):
    lenient = Problems(strict=False)
    with caplog.at_level(logging.WARNING, logger="cvslam"):
        for _ in range(2):
            lenient.report("warning", "w")
            lenient.report("error", "e")
        lenient.report("warning", "quiet", log_warning=False)
    assert lenient == [Problem("warning", "w"), Problem("error", "e"), Problem("warning", "quiet")]
    assert [r.getMessage() for r in caplog.records] == ["w"]
    strict = Problems(strict=True)
    strict.report("warning", "w")
    with pytest.raises(LogError, match=r"^bad$"):
        strict.report("error", "bad")
    assert strict == [Problem("warning", "w")]
