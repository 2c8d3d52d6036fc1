"""Decoded ROS 2 messages to typed records; non-finite numbers give no record."""

from __future__ import annotations

from types import SimpleNamespace as Msg

import numpy as np

from cvslam_cli.io.ros_messages import CONVERTERS, stamp_ns_of
from cvslam_cli.records.log import ImuSample, OdometryRecord, PoseRecord


def _xyz(x, y, z):
    return Msg(x=x, y=y, z=z)


def _quat(x, y, z, w):
    return Msg(x=x, y=y, z=z, w=w)


HEADER = Msg(stamp=Msg(sec=3, nanosec=25), frame_id="uav1/base_link")


def test_stamp_in_integer_nanoseconds():
    assert stamp_ns_of(Msg(header=HEADER)) == 3_000_000_025


def test_imu_odometry_and_pose_records():
    imu = Msg(
        header=HEADER, angular_velocity=_xyz(0.1, 0.2, 0.3), linear_acceleration=_xyz(1, 2, 9.8)
    )
    rec = CONVERTERS["imu"]("uav1", 7, imu)
    assert isinstance(rec, ImuSample) and rec.frame_id == "uav1/base_link"
    np.testing.assert_array_equal(rec.gyro_rad_s, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(rec.accel_m_s2, [1, 2, 9.8])
    pose = Msg(position=_xyz(1, 2, 3), orientation=_quat(0, 0, 0, 1))
    odom = Msg(
        header=HEADER,
        child_frame_id="uav1/base_link",
        pose=Msg(pose=pose, covariance=np.arange(36.0)),
        twist=Msg(twist=Msg(linear=_xyz(4, 5, 6), angular=_xyz(7, 8, 9)), covariance=np.ones(36)),
    )
    rec = CONVERTERS["odom"]("uav1", 7, odom)
    assert isinstance(rec, OdometryRecord) and rec.stamp_ns == 7
    np.testing.assert_array_equal(rec.position_m, [1, 2, 3])
    np.testing.assert_array_equal(rec.angular_rad_s, [7, 8, 9])
    assert rec.pose_cov.shape == rec.twist_cov.shape == (6, 6) and rec.pose_cov[1, 0] == 6
    rec = CONVERTERS["ground_truth"]("uav1", 7, Msg(header=HEADER, pose=pose))
    assert isinstance(rec, PoseRecord) and rec.frame_id == "uav1/base_link"
    np.testing.assert_array_equal(rec.q_xyzw, [0, 0, 0, 1])
    assert set(CONVERTERS) == {"imu", "odom", "ground_truth"}  # camera_info: no record


def test_non_finite_numbers_give_no_record():
    nan = float("nan")
    imu = Msg(header=HEADER, angular_velocity=_xyz(0, nan, 0), linear_acceleration=_xyz(0, 0, 0))
    assert CONVERTERS["imu"]("uav1", 7, imu) is None
    pose = Msg(header=HEADER, pose=Msg(position=_xyz(0, 0, 0), orientation=_quat(0, 0, 0, np.inf)))
    assert CONVERTERS["ground_truth"]("uav1", 7, pose) is None
