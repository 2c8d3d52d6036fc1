"""Stamps that cannot be used are dropped and counted (issue 16): before 1970, astray,
duplicated messages (and the same log given twice), out of order beyond the reorder window;
an image whose size changes mid-stream, and CameraInfo with the wrong number of coefficients,
are errors naming the topic."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import CvslamError, LogError
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.mcap_writer import LogWriter
from cvslam_cli.records.log import StereoFrame
from tests.synth import camera, write_image_log, write_stereo_log

S = 10**9
DT = 50_000_000


def _frames(paths, strict=True):
    logs = LogSet([McapLogSource(p) for p in paths], load_config().logs, strict=strict)
    frames = [r.stamp_ns for r in logs.records() if isinstance(r, StereoFrame)]
    return frames, [p.text for p in logs.problems]


def _dropped(problems, topic, n, why):
    return [p for p in problems if f"{topic}: dropped {n} message(s) {why}" in p]


LEFT = "/uav1/stereo/left/image_raw"


@pytest.mark.parametrize(
    ("stamps", "kept", "why"),
    [
        ([-5 * S] + [S + i * DT for i in range(6)], 6, "stamped before 1970"),
        (
            [S + i * DT for i in range(3)] + [(2**31 - 1) * S] + [S + i * DT for i in range(3, 6)],
            6,
            "stamped more than a day away",
        ),
        (
            [S + i * DT for i in (0, 1, 2, 3, 4, 5, 6, 7, 8, 9)] + [S + DT // 2, S + 10 * DT],
            11,
            "stamped earlier than a message already passed on",
        ),
    ],
)
def test_unusable_stamps_are_dropped_and_counted(tmp_path, stamps, kept, why):
    log = write_image_log(tmp_path / "a.mcap", stamps)
    frames, problems = _frames([log])
    assert len(frames) == kept and frames == sorted(frames)
    assert max(frames) < 10 * S  # no absurd stamp reached a record
    assert _dropped(problems, LEFT, 1, why), problems


def test_duplicated_messages_and_the_same_log_twice_do_not_double_the_frames(tmp_path):
    dup = write_image_log(tmp_path / "dup.mcap", [S + i * DT for i in (0, 1, 1, 2, 3, 3, 4)])
    frames, problems = _frames([dup])
    assert frames == [S + i * DT for i in range(5)]
    assert _dropped(problems, LEFT, 2, "repeating an earlier message"), problems
    synth = write_stereo_log(tmp_path / "one.mcap", n_frames=6)
    once, _ = _frames([synth.path])
    twice, problems = _frames([synth.path, synth.path])
    assert twice == once and len(once) == 6
    assert _dropped(problems, LEFT, 6, "repeating an earlier message"), problems
    assert any("/uav1/imu: dropped" in p for p in problems)


def test_same_stamp_other_content_is_kept(tmp_path):
    """Two different images with one stamp are not duplicates (pairing decides what to do)."""
    log = write_image_log(
        tmp_path / "a.mcap", [S, S + DT, S + DT, S + 2 * DT], repeat_content=False
    )
    _, problems = _frames([log], strict=False)
    assert not [p for p in problems if "repeating" in p]


def test_image_size_changing_mid_stream_is_an_error_naming_the_topic(tmp_path):
    sizes = [(64, 48)] * 3 + [(80, 60)] * 3
    log = write_image_log(tmp_path / "a.mcap", [S + i * DT for i in range(6)], sizes=sizes)
    with pytest.raises(LogError, match=rf"{LEFT}: image size changes from 64x48 to 80x60"):
        _frames([log])
    frames, problems = _frames([log], strict=False)
    assert len(frames) == 3
    assert len([p for p in problems if "image size changes" in p]) == 2  # once per topic


@pytest.mark.parametrize(
    ("model", "n", "ok"),
    [
        ("plumb_bob", 3, False),
        ("plumb_bob", 100, False),
        ("plumb_bob", 5, True),
        ("equidistant", 5, False),
        ("rational_polynomial", 8, True),
    ],
)
def test_camera_info_coefficient_count(tmp_path, model, n, ok):
    left = dataclasses.replace(
        camera(frame_id="uav1/left_camera_optical"), D=np.full(n, 1e-3), distortion_model=model
    )
    right = camera(right=True, frame_id="uav1/right_camera_optical")
    rng = np.random.default_rng(0)
    path = tmp_path / "a.mcap"
    with LogWriter(path) as w:
        w.write_tf_static(
            "/tf_static",
            S,
            [("uav1/base_link", c.frame_id, c.T_body_cam) for c in (left, right)],
        )
        for i in range(4):
            for side, cam in (("left", left), ("right", right)):
                img = rng.integers(0, 256, (48, 64), dtype=np.uint8)
                w.write_image(f"/uav1/stereo/{side}/image_raw", S + i * DT, img, cam.frame_id)
                w.write_camera_info(f"/uav1/stereo/{side}/camera_info", S + i * DT, cam)
    logs = LogSet([McapLogSource(path)], load_config().logs)
    if ok:
        assert logs.rig("uav1").left.D.size == n
    else:
        with pytest.raises(
            CvslamError, match=rf"{model} distortion takes .* coefficients, got {n}"
        ):
            logs.rig("uav1")


def test_imu_schema_lacking_fields_is_an_error_naming_the_topic(tmp_path):
    from mcap_ros2.writer import Writer

    path = tmp_path / "a.mcap"
    header = "std_msgs/Header header\n" + "=" * 80 + "\nMSG: std_msgs/Header\n"
    header += "builtin_interfaces/Time stamp\nstring frame_id\n" + "=" * 80
    header += "\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
    with path.open("wb") as f:
        w = Writer(f)
        schema = w.register_msgdef("sensor_msgs/msg/Imu", header)  # no rates, no forces
        for i in range(5):
            t = S + i * 5_000_000
            msg = {"header": {"stamp": {"sec": t // S, "nanosec": t % S}, "frame_id": "b"}}
            w.write_message("/uav1/imu", schema, msg, log_time=t, publish_time=t)
        w.finish()
    logs = LogSet([McapLogSource(path)], load_config().logs)
    with pytest.raises(
        LogError, match=r"/uav1/imu: its sensor_msgs/msg/Imu messages lack the field"
    ):
        list(logs.records())
