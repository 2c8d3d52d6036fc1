"""Vehicles per log file: two robots recorded with the same topic names stay two vehicles when
each log is bound to its own (`NAME=PATH`, `logs.vehicles.NAME.log`); two logs holding one
vehicle's topics over the same time are an error, never a silent merge; logs recorded one
after the other (a recording in parts) are one vehicle."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import LogError
from cvslam_cli.io.log_open import split_log_args
from cvslam_cli.io.logs import bind_logs, open_logs
from cvslam_cli.records.log import StereoFrame
from tests.io.rosbag_fixtures import EUROC_TOPICS, euroc_messages, write_ros1, write_rosbag2

N_PAIRS = 4
# the topic names of EuRoC's own bags, for every vehicle; the TF body frame as recorded
EUROC_NAMES = [
    "logs.vehicle_defaults.topics.left_image=/cam0/image_raw",
    "logs.vehicle_defaults.topics.right_image=/cam1/image_raw",
    "logs.vehicle_defaults.topics.left_info=/cam0/camera_info",
    "logs.vehicle_defaults.topics.right_info=/cam1/camera_info",
    "logs.vehicle_defaults.topics.imu=/imu0",
    "logs.vehicle_defaults.rig.body_frame=uav1/base_link",
]


@pytest.fixture(scope="module")
def two_robots(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    mav0 = shared_data / "euroc_v101_micro" / "mav0"
    if not mav0.is_dir():
        pytest.skip(f"{mav0} not found")
    tmp = tmp_path_factory.mktemp("robots")
    euroc = euroc_messages(mav0, N_PAIRS, EUROC_TOPICS)
    ours = euroc_messages(mav0, N_PAIRS)
    half = len(ours) // 2
    return {
        "a": write_ros1(euroc, tmp / "robot_a.bag"),
        "b": write_rosbag2(euroc, tmp / "robot_b", storage="sqlite3"),
        "uav1_a": write_rosbag2(ours, tmp / "uav1_a"),
        "uav1_b": write_ros1(ours, tmp / "uav1_b.bag"),
        "first_half": write_rosbag2(ours[:half], tmp / "first_half"),
        "second_half": write_rosbag2(ours[half:], tmp / "second_half"),
    }


def _frames(logs, vehicle):
    return [r for r in logs.records(vehicles=[vehicle]) if isinstance(r, StereoFrame)]


@pytest.mark.realdata
def test_two_bags_with_the_same_topic_names_are_two_vehicles(two_robots):
    paths, bound = split_log_args([f"robot1={two_robots['a']}", f"robot2={two_robots['b']}"])
    assert paths == [] and set(bound) == {"robot1", "robot2"}
    cfg = bind_logs(load_config(overrides=EUROC_NAMES).logs, bound)
    logs = open_logs(paths, cfg)
    assert list(logs.vehicles) == ["robot1", "robot2"]
    assert logs.vehicles["robot1"].topic("imu") == "/imu0" == logs.vehicles["robot2"].topic("imu")
    f1, f2 = _frames(logs, "robot1"), _frames(logs, "robot2")
    assert len(f1) == len(f2) == N_PAIRS
    assert all(np.array_equal(x.left.image, y.left.image) for x, y in zip(f1, f2, strict=True))
    assert logs.rig("robot1").describe()["baseline_m"] == pytest.approx(0.110, abs=2e-3)
    imu = [r for r in logs.records(roles=("imu",))]
    assert {r.vehicle for r in imu} == {"robot1", "robot2"}


@pytest.mark.realdata
def test_the_same_topics_from_two_logs_at_once_are_an_error_naming_both(two_robots):
    cfg = load_config(overrides=[*EUROC_NAMES, "logs.vehicles.mav.kind=uav"]).logs
    logs = open_logs([two_robots["a"], two_robots["b"]], cfg)
    with pytest.raises(LogError, match=r"robot_a\.bag and .*robot_b.*both hold /.* same time"):
        list(logs.records())
    logs = open_logs([two_robots["uav1_a"], two_robots["uav1_b"]], load_config().logs)
    assert list(logs.vehicles) == ["uav1"]  # discovered in both logs
    with pytest.raises(LogError, match=r"both hold /uav1/.* for vehicle uav1 .*NAME=PATH"):
        list(logs.records())


@pytest.mark.realdata
def test_a_recording_in_parts_is_one_vehicle(two_robots):
    logs = open_logs([two_robots["first_half"], two_robots["second_half"]], load_config().logs)
    assert list(logs.vehicles) == ["uav1"] and logs.vehicles["uav1"].sources == (0, 1)
    assert len(_frames(logs, "uav1")) == N_PAIRS


@pytest.mark.realdata
def test_a_bound_log_of_another_name_is_that_vehicle(two_robots):
    """Logs recorded as vehicle uav1 bound to robot1 and robot2, in the config's shorthand:
    the topics and TF frames of each log are its uav1's."""
    cfg = load_config(
        overrides=[
            f"logs.vehicles={{robot1: {two_robots['uav1_a']}, robot2: {two_robots['uav1_b']}}}"
        ]
    ).logs
    assert cfg.vehicles["robot1"].log == str(two_robots["uav1_a"])
    logs = open_logs([], cfg)
    assert list(logs.vehicles) == ["robot1", "robot2"]
    assert logs.vehicles["robot2"].template_name == "uav1"
    assert logs.rig("robot2").describe() == logs.rig("robot1").describe()
    assert len(_frames(logs, "robot2")) == N_PAIRS


@pytest.mark.realdata
def test_a_bound_log_without_the_vehicle_topics_lists_what_it_holds(two_robots):
    cfg = bind_logs(load_config().logs, {"robot1": two_robots["a"]})
    with pytest.raises(LogError, match=r"robot_a\.bag: none of vehicle robot1's topics .*/imu0"):
        open_logs([], cfg)


@pytest.mark.realdata
def test_cli_info_reads_two_robots_and_exits_1_when_no_vehicle(two_robots, cvslam):
    sets = [a for s in EUROC_NAMES for a in ("--set", s)]
    res = cvslam("info", f"robot1={two_robots['a']}", f"robot2={two_robots['b']}", *sets)
    assert res.code == 0, res.err
    assert "vehicle robot1" in res.out and "vehicle robot2" in res.out
    res = cvslam("info", two_robots["a"])
    assert res.code == 1
    assert "no vehicle found; topics seen: /cam0/camera_info" in res.err
    assert "/imu0 (sensor_msgs/msg/Imu)" in res.err


@pytest.mark.realdata
def test_later_stages_read_each_vehicle_from_the_log_extract_bound_it_to(
    two_robots, cvslam, tmp_path
):
    from cvslam_cli.io.logs import with_run_bindings

    sets = [a for s in EUROC_NAMES for a in ("--set", s)]
    run = tmp_path / "run"
    res = cvslam("-q", "extract", f"robot1={two_robots['a']}", f"robot2={two_robots['b']}",
                 "-o", run, *sets)  # fmt: skip
    assert res.code == 0, res.err
    assert sorted(p.name for p in (run / "features").glob("*.npz")) == ["robot1.npz", "robot2.npz"]
    plain = load_config(overrides=EUROC_NAMES).logs
    assert open_logs([two_robots["a"]], plain).vehicles == {}  # told nothing: no vehicle
    cfg = with_run_bindings(plain, run)
    assert cfg.vehicles["robot2"].log == str(two_robots["b"].resolve())
    assert list(open_logs([], cfg).vehicles) == ["robot1", "robot2"]
