from __future__ import annotations

import numpy as np
import pytest
from mcap_ros2._dynamic import serialize_dynamic

from cvslam_cli.io.mcap_writer import _quat, _vec, header, imu_cdr, path_cdr, path_fields
from cvslam_cli.io.ros2_msgdefs import msgdef_text


@pytest.mark.parametrize("frame_id", ["", "a", "xy", "uav1/base_link", "abcdefg"])
def test_fast_imu_encoding_equals_the_generic_encoder(frame_id):
    encode = serialize_dynamic("sensor_msgs/msg/Imu", msgdef_text("sensor_msgs/msg/Imu"))
    fields = {
        "header": header(1_700_000_000_123_456_789, frame_id),
        "orientation": _quat([0, 0, 0, 1]),
        "orientation_covariance": [-1.0] + [0.0] * 8,
        "angular_velocity": _vec([0.1, -0.2, 0.3]),
        "angular_velocity_covariance": list((np.eye(3) * 0.5).reshape(9)),
        "linear_acceleration": _vec([1.5, 2.5, -9.8]),
        "linear_acceleration_covariance": list((np.eye(3) * 0.25).reshape(9)),
    }
    expected = encode["sensor_msgs/msg/Imu"](fields)
    got = imu_cdr(
        1_700_000_000_123_456_789, frame_id, [0.1, -0.2, 0.3], [1.5, 2.5, -9.8], 0.5, 0.25
    )
    assert got == expected


@pytest.mark.parametrize("frame_id", ["", "a", "xyz", "nav", "uav1/base_link", "abcdefg"])
@pytest.mark.parametrize("n", [0, 1, 2, 5])
def test_fast_path_encoding_equals_the_generic_encoder(frame_id, n):
    encode = serialize_dynamic("nav_msgs/msg/Path", msgdef_text("nav_msgs/msg/Path"))
    rng = np.random.default_rng(n)
    stamps = 1_700_000_000_000_000_000 + rng.integers(0, 10**12, n)
    p, q = rng.normal(size=(n, 3)), rng.normal(size=(n, 4))
    expected = encode["nav_msgs/msg/Path"](path_fields(123_456_789_012, stamps, p, q, frame_id))
    assert path_cdr(123_456_789_012, frame_id, stamps, p, q) == expected
