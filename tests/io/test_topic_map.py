"""Topics to vehicles and roles: discovery from the templates, configured vehicles, the
compressed fallback, and the errors for topics missing, shared or of the wrong type."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import LogError
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource, TopicInfo
from cvslam_cli.io.topic_map import map_topics
from tests.synth import write_stereo_log

IMAGE = "sensor_msgs/msg/Image"
IMU = "sensor_msgs/msg/Imu"


@dataclass
class _Listing:
    """A log that only lists its topics (topic -> type, one message each)."""

    types: dict[str, str]
    name: str = "x.mcap"
    warnings: list[str] = field(default_factory=list)

    def topics(self) -> dict[str, TopicInfo]:
        return {t: TopicInfo(t, s, 1) for t, s in self.types.items()}


def _map(*logs: _Listing, overrides=()):
    return map_topics(logs, load_config(overrides=overrides).logs, "x.mcap")


def test_configured_topic_absent_is_an_error(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap")
    cfg = load_config(overrides=["logs.vehicles.uav1.topics.imu=/uav1/imu_typo"]).logs
    with pytest.raises(LogError, match=r"topic /uav1/imu_typo .*is not in the log"):
        LogSet([McapLogSource(synth.path)], cfg)
    cfg = load_config(overrides=["logs.vehicles.ghost.kind=uav"]).logs
    with pytest.raises(LogError, match="none of vehicle ghost's topics"):
        LogSet([McapLogSource(synth.path)], cfg)


def test_vehicles_discovered_from_the_topic_templates():
    topics = _map(
        _Listing(
            {
                "/uav2/imu": IMU,
                "/uav1/stereo/left/image_raw/compressed": "sensor_msgs/msg/CompressedImage",
                "/uav1/stereo/right/image_raw": IMAGE,
                "/rosout": "rcl_interfaces/msg/Log",
            }
        ),
        _Listing({"/uav1/imu": IMU}, name="y.mcap"),
    )
    assert list(topics.vehicles) == ["uav1", "uav2"]
    uav1 = topics.vehicles["uav1"]
    assert uav1.present == ("left_image", "right_image", "imu") and uav1.has_stereo
    assert uav1.topic("left_image") == "/uav1/stereo/left/image_raw/compressed"
    assert not topics.vehicles["uav2"].has_stereo
    assert topics.role_of[(1, "/uav1/imu")] == ("uav1", "imu")
    assert uav1.sources == (0, 1) and topics.vehicles["uav2"].sources == (0,)
    assert topics.logs_of == {
        "/uav2/imu": [0],
        "/uav1/stereo/left/image_raw/compressed": [0],
        "/uav1/stereo/right/image_raw": [0],
        "/rosout": [0],
        "/uav1/imu": [1],
    }
    assert [i.topic for i in topics.unassigned()] == ["/rosout"]


def test_configured_vehicles_only_and_message_counts_summed():
    a, b = _Listing({"/uav1/imu": IMU, "/uav2/imu": IMU}), _Listing({"/uav1/imu": IMU})
    topics = _map(a, b, overrides=["logs.vehicles.uav1.kind=uav"])
    assert list(topics.vehicles) == ["uav1"]
    assert topics.infos["/uav1/imu"].message_count == 2
    assert topics.logs_of["/uav1/imu"] == [0, 1]
    assert [i.topic for i in topics.unassigned()] == ["/uav2/imu"]


def test_a_topic_of_two_vehicles_or_of_the_wrong_type_is_an_error():
    shared = ["logs.vehicles.a.topics.imu=/imu", "logs.vehicles.b.topics.imu=/imu"]
    both = r"topic /imu is mapped twice: as vehicle a's imu \(logs\.vehicles\.a\.topics\.imu\) "
    with pytest.raises(LogError, match=both + r"and as vehicle b's imu \(logs\.vehicles\.b"):
        _map(_Listing({"/imu": IMU}), overrides=shared)
    with pytest.raises(LogError, match=r"/uav1/imu: has type .*Image, expected .*Imu for uav1"):
        _map(_Listing({"/uav1/imu": IMAGE}))
    with pytest.raises(LogError, match=r"y.mcap: /uav1/imu: type .*Image differs from .*Imu"):
        _map(_Listing({"/uav1/imu": IMU}), _Listing({"/uav1/imu": IMAGE}, name="y.mcap"))


def test_logs_bound_to_two_vehicles_may_type_a_topic_differently():
    pose, point = "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PointStamped"
    a = _Listing({"/gt": pose, "/imu": IMU}, name="a.bag")
    b = _Listing({"/gt": point, "/imu": IMU}, name="b.bag")
    names = [
        "logs.vehicle_defaults.topics.ground_truth=/gt",
        "logs.vehicle_defaults.topics.imu=/imu",
    ]
    topics = _map(a, b, overrides=[*names, "logs.vehicles={r1: a.bag, r2: b.bag}"])
    assert topics.vehicles["r1"].infos["ground_truth"].schema_name == pose
    assert topics.vehicles["r2"].infos["ground_truth"].schema_name == point
    assert topics.role_of[(1, "/gt")] == ("r2", "ground_truth")
    with pytest.raises(LogError, match=r"b\.bag: /gt: type .*PointStamped differs"):
        _map(a, b, overrides=[*names, "logs.vehicles.r1.kind=uav"])
