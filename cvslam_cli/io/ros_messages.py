"""Decoded ROS 2 messages -> typed records (`io/records.py`).

A message whose numbers are not all finite gives no record (None): the caller counts it as
dropped. Images are decoded by `io/images.py`; camera calibration by `io/calibration.py`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from cvslam_cli.records.log import ImuSample, OdometryRecord, PoseRecord, Record


def stamp_ns_of(msg: Any) -> int:
    """A message's header stamp in integer nanoseconds."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def imu_sample(vehicle: str, stamp_ns: int, msg: Any) -> ImuSample | None:
    """sensor_msgs/msg/Imu -> ImuSample (angular rate and specific force in the message frame)."""
    w, a = msg.angular_velocity, msg.linear_acceleration
    gyro = np.array([w.x, w.y, w.z], dtype=float)
    acc = np.array([a.x, a.y, a.z], dtype=float)
    if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(acc))):
        return None
    return ImuSample(vehicle, stamp_ns, gyro, acc, str(msg.header.frame_id))


def odometry_record(vehicle: str, stamp_ns: int, msg: Any) -> OdometryRecord | None:
    """nav_msgs/msg/Odometry -> OdometryRecord (pose, twist and their covariances)."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    vals = np.array(
        [p.x, p.y, p.z, q.x, q.y, q.z, q.w, lin.x, lin.y, lin.z, ang.x, ang.y, ang.z],
        dtype=float,
    )
    if not np.all(np.isfinite(vals)):
        return None
    return OdometryRecord(
        vehicle,
        stamp_ns,
        str(msg.header.frame_id),
        str(msg.child_frame_id),
        vals[0:3],
        vals[3:7],
        vals[7:10],
        vals[10:13],
        np.asarray(msg.pose.covariance).reshape(6, 6),
        np.asarray(msg.twist.covariance).reshape(6, 6),
    )


def _pose_of(msg: Any) -> tuple[Any, Any | None]:
    """(position, orientation or None) of any ground-truth message type: PoseStamped,
    PoseWithCovarianceStamped, Odometry (`pose.pose`), TransformStamped (`transform`),
    PointStamped (`point`, no orientation)."""
    if hasattr(msg, "transform"):
        return msg.transform.translation, msg.transform.rotation
    if hasattr(msg, "point"):
        return msg.point, None
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    return pose.position, pose.orientation


def pose_record(vehicle: str, stamp_ns: int, msg: Any) -> PoseRecord | None:
    """A ground-truth message (`GROUND_TRUTH_TYPES`) -> PoseRecord (position and quaternion
    in its frame; a PointStamped has no orientation: its quaternion is NaN)."""
    p, q = _pose_of(msg)
    pos = np.array([p.x, p.y, p.z], dtype=float)
    quat = np.full(4, np.nan) if q is None else np.array([q.x, q.y, q.z, q.w], dtype=float)
    if not (np.all(np.isfinite(pos)) and (q is None or np.all(np.isfinite(quat)))):
        return None
    return PoseRecord(vehicle, stamp_ns, str(msg.header.frame_id), pos, quat)


GROUND_TRUTH_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PointStamped",
)


CONVERTERS: dict[str, Callable[[str, int, Any], Record | None]] = {
    "imu": imu_sample,
    "odom": odometry_record,
    "ground_truth": pose_record,
}
"""The converter of each non-image role with a record (camera_info topics have none)."""
