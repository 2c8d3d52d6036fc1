"""The standard ROS 2 message definitions cvslam writes (fields of the upstream .msg files).

MCAP files written with the `ros2msg` schema encoding carry each type's definition followed
by the definitions of every type it uses, separated as rosbag2 does. Keeping the upstream
field lists exactly (names, types, fixed array sizes, order) is what lets other tools
(Foxglove, rosbags, ros2 bag) decode the files.
"""

from __future__ import annotations

import re

_SEPARATOR = "=" * 80

MSG_FIELDS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/msg/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose",
    "geometry_msgs/msg/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "std_msgs/Header header\n"
    "geometry_msgs/PoseWithCovariance pose",
    "geometry_msgs/msg/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular",
    "geometry_msgs/msg/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance",
    "geometry_msgs/msg/Transform": "geometry_msgs/Vector3 translation\n"
    "geometry_msgs/Quaternion rotation",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\n"
    "geometry_msgs/Transform transform",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "sensor_msgs/msg/Image": "std_msgs/Header header\nuint32 height\nuint32 width\n"
    "string encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data",
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "sensor_msgs/msg/RegionOfInterest": "uint32 x_offset\nuint32 y_offset\nuint32 height\n"
    "uint32 width\nbool do_rectify",
    "sensor_msgs/msg/CameraInfo": "std_msgs/Header header\nuint32 height\nuint32 width\n"
    "string distortion_model\nfloat64[] d\nfloat64[9] k\n"
    "float64[9] r\nfloat64[12] p\nuint32 binning_x\n"
    "uint32 binning_y\nsensor_msgs/RegionOfInterest roi",
    "sensor_msgs/msg/Imu": "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
    "float64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\n"
    "float64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\n"
    "float64[9] linear_acceleration_covariance",
    "sensor_msgs/msg/PointField": "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\n"
    "uint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\n"
    "uint8 FLOAT64=8\nstring name\nuint32 offset\n"
    "uint8 datatype\nuint32 count",
    "sensor_msgs/msg/PointCloud2": "std_msgs/Header header\nuint32 height\nuint32 width\n"
    "sensor_msgs/PointField[] fields\nbool is_bigendian\n"
    "uint32 point_step\nuint32 row_step\nuint8[] data\n"
    "bool is_dense",
    "nav_msgs/msg/Odometry": "std_msgs/Header header\nstring child_frame_id\n"
    "geometry_msgs/PoseWithCovariance pose\n"
    "geometry_msgs/TwistWithCovariance twist",
    "nav_msgs/msg/Path": "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses",
}

_TYPE_RE = re.compile(r"^([A-Za-z0-9_]+)/([A-Za-z0-9_]+)")


def _full_name(short: str) -> str:
    pkg, name = short.split("/")
    return f"{pkg}/msg/{name}"


def _dependencies(datatype: str) -> list[str]:
    """All types `datatype` uses, depth first, each once."""
    seen: list[str] = []

    def visit(t: str) -> None:
        for line in MSG_FIELDS[t].splitlines():
            m = _TYPE_RE.match(line)
            if m:
                dep = _full_name(f"{m.group(1)}/{m.group(2)}")
                if dep not in seen:
                    seen.append(dep)
                    visit(dep)

    visit(datatype)
    return seen


def msgdef_text(datatype: str) -> str:
    """The concatenated definition of `datatype` (e.g. "sensor_msgs/msg/Image")."""
    if datatype not in MSG_FIELDS:
        raise KeyError(f"no ROS 2 message definition for {datatype}")
    parts = [MSG_FIELDS[datatype]]
    for dep in _dependencies(datatype):
        pkg, _, name = dep.split("/")
        parts.append(f"{_SEPARATOR}\nMSG: {pkg}/{name}\n{MSG_FIELDS[dep]}")
    return "\n".join(parts) + "\n"
