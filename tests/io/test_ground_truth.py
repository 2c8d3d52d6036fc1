"""Ground truth of every usual type and file format: the real EuRoC clip's ground truth
written (by `rosbags`) as PoseStamped, PoseWithCovarianceStamped, TransformStamped, Odometry
and PointStamped, and as TUM, EuRoC CSV and KITTI files, reads back as the same trajectory;
its world frame is converted to NED once, as stated (`ground_truth_frame`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from cvslam_cli.config import load_config
from cvslam_cli.geometry.nav_frames import GROUND_TRUTH_FRAMES, table_to_nav
from cvslam_cli.io.importers.euroc import world_to_ned
from cvslam_cli.io.logs import ground_truth_tables, open_logs
from cvslam_cli.io.trajectory import read_trajectory_file, read_tum, write_kitti
from cvslam_cli.records.poses import PoseTable
from tests.io.rosbag_fixtures import ROS2

TOPIC = "/uav1/ground_truth/pose"
TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PointStamped",
)


@pytest.fixture(scope="module")
def truth(shared_data: Path) -> PoseTable:
    path = shared_data / "euroc_v101_micro/mav0/state_groundtruth_estimate0/groundtruth.tum"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    return read_tum(path)


def _message(msgtype: str, st: int, p: np.ndarray, q: np.ndarray):
    T = ROS2.types
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=st // 10**9, nanosec=st % 10**9),
        frame_id="world",
    )
    point = T["geometry_msgs/msg/Point"](*p)
    quat = T["geometry_msgs/msg/Quaternion"](*q)
    pose = T["geometry_msgs/msg/Pose"](position=point, orientation=quat)
    cov = np.zeros(36)
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return T[msgtype](header=header, pose=pose)
    if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        return T[msgtype](header=header, pose=T["geometry_msgs/msg/PoseWithCovariance"](pose, cov))
    if msgtype == "geometry_msgs/msg/TransformStamped":
        tr = T["geometry_msgs/msg/Transform"](T["geometry_msgs/msg/Vector3"](*p), quat)
        return T[msgtype](header=header, child_frame_id="uav1/base_link", transform=tr)
    if msgtype == "nav_msgs/msg/Odometry":
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            T["geometry_msgs/msg/Twist"](
                T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                T["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
            ),
            cov,
        )
        return T[msgtype](
            header=header,
            child_frame_id="uav1/base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose, cov),
            twist=twist,
        )
    return T[msgtype](header=header, point=point)


def _bag(truth: PoseTable, msgtype: str, out: Path) -> Path:
    with Writer2(out, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(TOPIC, msgtype, typestore=ROS2)
        for st, p, q in zip(truth.stamps_ns, truth.p_nav_m, truth.q_nav_body_xyzw, strict=True):
            msg = _message(msgtype, int(st), p, q)
            w.write(conn, int(st), ROS2.serialize_cdr(msg, msgtype))
    return out


def _read(bag: Path, frame: str = "ned") -> PoseTable:
    cfg = load_config(overrides=[f"logs.vehicle_defaults.ground_truth_frame={frame}"]).logs
    return ground_truth_tables(open_logs([bag], cfg), ["uav1"])["uav1"]


@pytest.mark.realdata
def test_every_ground_truth_type_gives_the_pose_stamped_trajectory(truth, tmp_path):
    ref = _read(_bag(truth, TYPES[0], tmp_path / "pose"))
    assert len(ref) == len(truth) == 95
    assert np.array_equal(ref.stamps_ns, truth.stamps_ns)
    assert np.array_equal(ref.p_nav_m, truth.p_nav_m)
    for i, msgtype in enumerate(TYPES[1:]):
        got = _read(_bag(truth, msgtype, tmp_path / f"t{i}"))
        assert np.array_equal(got.stamps_ns, ref.stamps_ns), msgtype
        assert np.array_equal(got.p_nav_m, ref.p_nav_m), msgtype
        if msgtype.endswith("PointStamped"):  # position only
            assert np.all(np.isnan(got.q_nav_body_xyzw))
        else:
            assert np.array_equal(got.q_nav_body_xyzw, ref.q_nav_body_xyzw), msgtype


@pytest.mark.realdata
def test_the_stated_world_frame_is_converted_to_ned_once(truth, tmp_path):
    bag = _bag(truth, TYPES[2], tmp_path / "tf")
    got = _read(bag, "enu")  # EuRoC's Vicon world: x, y horizontal, z up
    ref = world_to_ned(truth.stamps_ns, truth.p_nav_m, truth.q_nav_body_xyzw)  # the importer's
    assert np.allclose(got.p_nav_m, ref.p_nav_m, atol=1e-12)
    dots = np.abs(np.sum(got.q_nav_body_xyzw * ref.q_nav_body_xyzw, axis=1))
    assert np.allclose(dots, 1.0, atol=1e-12)
    assert set(GROUND_TRUTH_FRAMES) == {"ned", "enu", "nwu", "camera"}
    # camera: forward (z) is north, right (x) east, down (y) down
    cam = table_to_nav(
        PoseTable(np.array([0]), np.array([[1.0, 2.0, 3.0]]), np.array([[0.0, 0.0, 0.0, 1.0]])),
        "camera",
    )
    assert np.allclose(cam.p_nav_m, [[3.0, 1.0, 2.0]])


@pytest.mark.realdata
def test_tum_euroc_csv_and_kitti_files_give_the_same_trajectory(truth, tmp_path, shared_data):
    csv = tmp_path / "data.csv"
    rows = [
        ",".join([str(st), *(repr(float(v)) for v in (*p, q[3], *q[:3])), *["0"] * 9])
        for st, p, q in zip(truth.stamps_ns, truth.p_nav_m, truth.q_nav_body_xyzw, strict=True)
    ]
    csv.write_text("#timestamp, p_RS_R_x [m], ...\n" + "\n".join(rows) + "\n")
    got = read_trajectory_file(csv)
    assert np.array_equal(got.stamps_ns, truth.stamps_ns)
    assert np.array_equal(got.p_nav_m, truth.p_nav_m)
    assert np.array_equal(got.q_nav_body_xyzw, truth.q_nav_body_xyzw)
    kitti = tmp_path / "poses.txt"
    write_kitti(kitti, truth)
    k = read_trajectory_file(kitti)
    assert len(k) == len(truth) and np.allclose(k.p_nav_m, truth.p_nav_m, atol=1e-12)
    real = read_trajectory_file(shared_data / "reference_trajectories" / "V102_groundtruth.csv")
    assert len(real) > 1000 and real.stamps_ns[0] == 1403715524907143168
    assert np.allclose(real.p_nav_m[0], [0.515356, 1.996773, 0.971104])
    assert np.allclose(real.q_nav_body_xyzw[0], [0.789985, -0.205376, 0.554528, 0.161996])
