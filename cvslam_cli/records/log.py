"""The records a log gives: images, stereo pairs, IMU samples, odometry, poses.

All times are integer nanoseconds (`stamp_ns`, the message header stamp). Arrays are float64
unless stated. Frames: poses are in the nav frame (NED) unless the record says otherwise;
IMU samples are in the frame named by `frame_id` (the body frame for cvslam's own logs).
"""

from __future__ import annotations

from dataclasses import dataclass

from numpy.typing import NDArray

from cvslam_cli.records.arrays import F64


@dataclass(frozen=True, eq=False)
class ImageRecord:
    """One decoded image. `image`: (H, W) grey or (H, W, 3) BGR, uint8 or uint16. `vehicle`:
    whose camera took it (two vehicles' logs may use the same topic names)."""

    stamp_ns: int
    image: NDArray
    encoding: str
    frame_id: str
    topic: str
    vehicle: str = ""

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])


@dataclass(frozen=True, eq=False)
class StereoFrame:
    """A left/right image pair whose stamps differ by at most the pairing tolerance.
    `stamp_ns` is the left image's stamp."""

    vehicle: str
    stamp_ns: int
    left: ImageRecord
    right: ImageRecord

    @property
    def pair_offset_ns(self) -> int:
        return self.right.stamp_ns - self.left.stamp_ns


@dataclass(frozen=True, eq=False)
class ImuSample:
    """Angular rate (3,) rad/s and specific force (3,) m/s^2 in frame `frame_id`."""

    vehicle: str
    stamp_ns: int
    gyro_rad_s: F64
    accel_m_s2: F64
    frame_id: str


@dataclass(frozen=True, eq=False)
class OdometryRecord:
    """nav_msgs/Odometry: pose of `child_frame_id` in `frame_id`; twist in `child_frame_id`.
    position_m (3,), q_xyzw (4,), linear_m_s (3,), angular_rad_s (3,), pose_cov (6, 6),
    twist_cov (6, 6)."""

    vehicle: str
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    position_m: F64
    q_xyzw: F64
    linear_m_s: F64
    angular_rad_s: F64
    pose_cov: F64
    twist_cov: F64


@dataclass(frozen=True, eq=False)
class PoseRecord:
    """A pose of the body in `frame_id` (normally the nav frame, for ground truth):
    p_m (3,), q_xyzw (4,) rotating body coordinates into `frame_id`."""

    vehicle: str
    stamp_ns: int
    frame_id: str
    p_m: F64
    q_xyzw: F64


Record = StereoFrame | ImuSample | OdometryRecord | PoseRecord
