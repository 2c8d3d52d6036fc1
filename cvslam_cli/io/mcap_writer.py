"""Writing ROS 2 MCAP logs with standard message definitions (readable by other tools).

`LogWriter` writes to `<path>.partial` and renames to `<path>` only when `close()` succeeds,
so an interrupted import or simulation never leaves a file that looks complete.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.rotations import matrix_to_quat_xyzw
from cvslam_cli.io.atomic import AtomicFile, AtomicWriter
from cvslam_cli.io.images import raw_fields
from cvslam_cli.io.ros2_msgdefs import msgdef_text


def stamp_fields(stamp_ns: int) -> dict[str, int]:
    """builtin_interfaces/Time fields of an integer nanosecond stamp."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": stamp_fields(stamp_ns), "frame_id": frame_id}


def _vec(v: Any) -> dict[str, float]:
    x, y, z = (float(a) for a in np.asarray(v).reshape(3))
    return {"x": x, "y": y, "z": z}


def _quat(q_xyzw: Any) -> dict[str, float]:
    x, y, z, w = (float(a) for a in np.asarray(q_xyzw).reshape(4))
    return {"x": x, "y": y, "z": z, "w": w}


def camera_info_fields(cam: CameraModel, stamp_ns: int) -> dict[str, Any]:
    P = cam.P if cam.P is not None else np.hstack([cam.K, np.zeros((3, 1))])
    return {
        "header": header(stamp_ns, cam.frame_id),
        "height": cam.height,
        "width": cam.width,
        "distortion_model": cam.distortion_model if cam.distortion_model != "none" else "",
        "d": [float(d) for d in cam.D],
        "k": [float(v) for v in np.asarray(cam.K).reshape(9)],
        "r": [float(v) for v in np.asarray(cam.R_rect).reshape(9)],
        "p": [float(v) for v in np.asarray(P).reshape(12)],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def pose_stamped_fields(stamp_ns: int, p_m: Any, q_xyzw: Any, frame_id: str) -> dict[str, Any]:
    """geometry_msgs/msg/PoseStamped fields."""
    return {
        "header": header(stamp_ns, frame_id),
        "pose": {"position": _vec(p_m), "orientation": _quat(q_xyzw)},
    }


def path_fields(
    stamp_ns: int, stamps_ns: Any, p_m: Any, q_xyzw: Any, frame_id: str
) -> dict[str, Any]:
    """nav_msgs/msg/Path fields: header at `stamp_ns`, one PoseStamped per row of `stamps_ns`
    (N,), `p_m` (N, 3), `q_xyzw` (N, 4)."""
    return {
        "header": header(stamp_ns, frame_id),
        "poses": [
            pose_stamped_fields(int(t), p, q, frame_id)
            for t, p, q in zip(
                np.asarray(stamps_ns).reshape(-1),
                np.asarray(p_m, dtype=float).reshape(-1, 3),
                np.asarray(q_xyzw, dtype=float).reshape(-1, 4),
                strict=True,
            )
        ],
    }


def pose_with_covariance_fields(
    stamp_ns: int, p_m: Any, q_xyzw: Any, cov: Any, frame_id: str
) -> dict[str, Any]:
    """geometry_msgs/msg/PoseWithCovarianceStamped fields; `cov` (6, 6) row-major."""
    return {
        "header": header(stamp_ns, frame_id),
        "pose": {
            "pose": {"position": _vec(p_m), "orientation": _quat(q_xyzw)},
            "covariance": [float(v) for v in np.asarray(cov, dtype=float).reshape(36)],
        },
    }


def tf_message_fields(stamp_ns: int, transforms: list[tuple[str, str, Any]]) -> dict[str, Any]:
    """tf2_msgs/msg/TFMessage fields: `transforms` (parent_frame, child_frame,
    T_parent_child 4x4), all stamped `stamp_ns`."""
    return {
        "transforms": [
            {
                "header": header(stamp_ns, parent),
                "child_frame_id": child,
                "transform": {
                    "translation": _vec(np.asarray(T)[:3, 3]),
                    "rotation": _quat(matrix_to_quat_xyzw(np.asarray(T)[:3, :3])),
                },
            }
            for parent, child, T in transforms
        ]
    }


# sensor_msgs/msg/PointField datatype constants by NumPy dtype
POINT_FIELD_DATATYPES: dict[np.dtype[Any], int] = {
    np.dtype("<i1"): 1,
    np.dtype("<u1"): 2,
    np.dtype("<i2"): 3,
    np.dtype("<u2"): 4,
    np.dtype("<i4"): 5,
    np.dtype("<u4"): 6,
    np.dtype("<f4"): 7,
    np.dtype("<f8"): 8,
}


def point_cloud2_fields(stamp_ns: int, frame_id: str, cloud: np.ndarray) -> dict[str, Any]:
    """sensor_msgs/msg/PointCloud2 fields of `cloud`, a (N,) NumPy structured array of
    little-endian scalar fields (e.g. x, y, z float32): one row, `point_step` the record
    size, PointField offsets from the dtype. `is_dense` when no float field holds NaN/inf."""
    cloud = np.ascontiguousarray(cloud).reshape(-1)
    if cloud.dtype.names is None:
        raise ValueError("point cloud: expected a structured array (named fields)")
    fields = []
    dense = True
    for name in cloud.dtype.names:
        dt, offset = cloud.dtype.fields[name][:2]
        datatype = POINT_FIELD_DATATYPES.get(dt)
        if datatype is None:
            raise ValueError(
                f"point cloud field {name!r}: dtype {dt} is not a little-endian "
                "int8/16/32, uint8/16/32, float32 or float64 scalar"
            )
        fields.append({"name": name, "offset": int(offset), "datatype": datatype, "count": 1})
        if dt.kind == "f":
            dense = dense and bool(np.isfinite(cloud[name]).all())
    step = cloud.dtype.itemsize
    return {
        "header": header(stamp_ns, frame_id),
        "height": 1,
        "width": len(cloud),
        "fields": fields,
        "is_bigendian": False,
        "point_step": step,
        "row_step": step * len(cloud),
        "data": cloud.tobytes(),
        "is_dense": dense,
    }


_IMU_TAIL = struct.Struct("<37d")


def imu_cdr(
    stamp_ns: int,
    frame_id: str,
    gyro_rad_s: Any,
    accel_m_s2: Any,
    gyro_var: float,
    accel_var: float,
) -> bytes:
    """CDR (little-endian) encoding of a sensor_msgs/msg/Imu with no orientation, the same
    bytes mcap-ros2-support produces (checked in the tests), without its per-message
    serialiser (BENCHMARKS.md, "Figures from docstrings")."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    name = frame_id.encode() + b"\0"
    head = struct.pack("<4siII", b"\0\x01\0\0", sec, nanosec, len(name)) + name
    head += b"\0" * (-(len(head) - 4) % 8)  # float64 fields align to 8 (after encapsulation)
    g, a = np.asarray(gyro_rad_s, dtype=float), np.asarray(accel_m_s2, dtype=float)
    return head + _IMU_TAIL.pack(
        0.0,
        0.0,
        0.0,
        1.0,
        -1.0,
        0,
        0,
        0,
        0,
        0,
        0,
        0,
        0,
        g[0],
        g[1],
        g[2],
        gyro_var,
        0,
        0,
        0,
        gyro_var,
        0,
        0,
        0,
        gyro_var,
        a[0],
        a[1],
        a[2],
        accel_var,
        0,
        0,
        0,
        accel_var,
        0,
        0,
        0,
        accel_var,
    )


def _pose_stamped_dtype(name_len: int, start: int) -> np.dtype[Any]:
    """The CDR record of one geometry_msgs/PoseStamped in a sequence, starting at payload
    offset `start` (a multiple of 4): stamp, frame_id (uint32 length with the NUL, the
    bytes), padding to 8, then position and orientation (7 float64)."""
    head = 12 + name_len
    pad = -(start + head) % 8
    return np.dtype(
        {
            "names": ["sec", "nanosec", "len", "name", "values"],
            "formats": ["<i4", "<u4", "<u4", f"S{name_len}", ("<f8", (7,))],
            "offsets": [0, 4, 8, 12, head + pad],
            "itemsize": head + pad + 56,
        }
    )


def path_cdr(stamp_ns: int, frame_id: str, stamps_ns: Any, p_m: Any, q_xyzw: Any) -> bytes:
    """CDR (little-endian) encoding of a nav_msgs/msg/Path (see `path_fields`), the same
    bytes mcap-ros2-support produces (checked in the tests), built with NumPy: a Path of a
    thousand poses costs a few milliseconds instead of a few hundred through the generic
    serialiser (the paths of result.mcap grow about once a second)."""
    name = frame_id.encode() + b"\0"
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    values = np.concatenate(
        [
            np.asarray(p_m, dtype=np.float64).reshape(-1, 3),
            np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4),
        ],
        axis=1,
    )
    n = len(stamps)
    if values.shape[0] != n:
        raise ValueError(f"path: {n} stamps but {values.shape[0]} poses")
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    head = struct.pack("<iII", sec, nanosec, len(name)) + name
    head += b"\0" * (-len(head) % 4) + struct.pack("<I", n)
    parts = [b"\0\x01\0\0", head]
    start = len(head)
    for rows in (slice(0, 1), slice(1, n)):  # the first record's padding may differ
        k = len(range(*rows.indices(n)))
        if not k:
            continue
        rec = np.zeros(k, dtype=_pose_stamped_dtype(len(name), start))
        rec["sec"], rec["nanosec"] = np.divmod(stamps[rows], 1_000_000_000)
        rec["len"] = len(name)
        rec["name"] = name
        rec["values"] = values[rows]
        parts.append(rec.tobytes())
        start += rec.nbytes
    return b"".join(parts)


class LogWriter(AtomicWriter):
    """A ROS 2 MCAP being written. Use as a context manager."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = 4 * 1024 * 1024,
        compression: str = "zstd",
    ) -> None:
        self.path = Path(path)
        self._atomic = AtomicFile(self.path)
        self._file = self._atomic.tmp.open("wb")
        comp = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }[compression]
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._schemas: dict[str, Schema] = {}
        self._raw_channels: dict[str, int] = {}
        self.count = 0

    def close(self) -> None:
        self._writer.finish()
        self._file.close()
        self._atomic.commit()

    def abort(self) -> None:
        self._file.close()
        self._atomic.discard()

    # -- generic -------------------------------------------------------------------------

    def write(
        self,
        topic: str,
        datatype: str,
        fields: dict[str, Any],
        stamp_ns: int,
        log_time_ns: int | None = None,
    ) -> None:
        t = int(stamp_ns if log_time_ns is None else log_time_ns)
        self._writer.write_message(
            topic, self._schema(datatype), fields, log_time=t, publish_time=t
        )
        self.count += 1

    def _schema(self, datatype: str) -> Schema:
        schema = self._schemas.get(datatype)
        if schema is None:
            schema = self._writer.register_msgdef(datatype, msgdef_text(datatype))
            self._schemas[datatype] = schema
        return schema

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer._writer.add_metadata(name, {k: str(v) for k, v in data.items()})

    # -- typed helpers -------------------------------------------------------------------

    def write_image(self, topic: str, stamp_ns: int, image: np.ndarray, frame_id: str) -> None:
        self.write(
            topic,
            "sensor_msgs/msg/Image",
            {"header": header(stamp_ns, frame_id), **raw_fields(image)},
            stamp_ns,
        )

    def write_compressed_image(
        self, topic: str, stamp_ns: int, image: np.ndarray, frame_id: str, fmt: str = "png"
    ) -> None:
        ok, buf = cv2.imencode(f".{fmt}", image)
        if not ok:
            raise ValueError(f"cannot encode image as {fmt}")
        self.write(
            topic,
            "sensor_msgs/msg/CompressedImage",
            {"header": header(stamp_ns, frame_id), "format": fmt, "data": buf.tobytes()},
            stamp_ns,
        )

    def write_camera_info(self, topic: str, stamp_ns: int, cam: CameraModel) -> None:
        self.write(topic, "sensor_msgs/msg/CameraInfo", camera_info_fields(cam, stamp_ns), stamp_ns)

    def write_raw(
        self,
        topic: str,
        datatype: str,
        payload: bytes,
        stamp_ns: int,
        log_time_ns: int | None = None,
    ) -> None:
        """Write an already CDR-encoded message (fast paths for high-rate topics)."""
        schema = self._schema(datatype)
        channel = self._raw_channels.get(topic)
        if channel is None:
            channel = self._writer._writer.register_channel(topic, "cdr", schema.id)
            self._raw_channels[topic] = channel
        t = int(stamp_ns if log_time_ns is None else log_time_ns)
        self._writer._writer.add_message(channel, log_time=t, data=payload, publish_time=t)
        self.count += 1

    def write_imu(
        self,
        topic: str,
        stamp_ns: int,
        gyro_rad_s: Any,
        accel_m_s2: Any,
        frame_id: str,
        gyro_var: float = 0.0,
        accel_var: float = 0.0,
        log_time_ns: int | None = None,
    ) -> None:
        """sensor_msgs/msg/Imu without orientation (covariance[0] = -1, REP 145)."""
        self.write_raw(
            topic,
            "sensor_msgs/msg/Imu",
            imu_cdr(stamp_ns, frame_id, gyro_rad_s, accel_m_s2, gyro_var, accel_var),
            stamp_ns,
            log_time_ns,
        )

    def write_pose(self, topic: str, stamp_ns: int, p_m: Any, q_xyzw: Any, frame_id: str) -> None:
        self.write(
            topic,
            "geometry_msgs/msg/PoseStamped",
            {
                "header": header(stamp_ns, frame_id),
                "pose": {"position": _vec(p_m), "orientation": _quat(q_xyzw)},
            },
            stamp_ns,
        )

    def write_odometry(
        self,
        topic: str,
        stamp_ns: int,
        frame_id: str,
        child_frame_id: str,
        p_m: Any,
        q_xyzw: Any,
        linear_m_s: Any,
        angular_rad_s: Any,
        pose_cov: Any = None,
        twist_cov: Any = None,
    ) -> None:
        pc = np.zeros(36) if pose_cov is None else np.asarray(pose_cov, float).reshape(36)
        tc = np.zeros(36) if twist_cov is None else np.asarray(twist_cov, float).reshape(36)
        self.write(
            topic,
            "nav_msgs/msg/Odometry",
            {
                "header": header(stamp_ns, frame_id),
                "child_frame_id": child_frame_id,
                "pose": {
                    "pose": {"position": _vec(p_m), "orientation": _quat(q_xyzw)},
                    "covariance": [float(v) for v in pc],
                },
                "twist": {
                    "twist": {"linear": _vec(linear_m_s), "angular": _vec(angular_rad_s)},
                    "covariance": [float(v) for v in tc],
                },
            },
            stamp_ns,
        )

    def write_tf_static(
        self, topic: str, stamp_ns: int, transforms: list[tuple[str, str, np.ndarray]]
    ) -> None:
        """`transforms`: (parent_frame, child_frame, T_parent_child 4x4)."""
        self.write(
            topic, "tf2_msgs/msg/TFMessage", tf_message_fields(stamp_ns, transforms), stamp_ns
        )

    def write_path(
        self,
        topic: str,
        stamp_ns: int,
        stamps_ns: Any,
        p_m: Any,
        q_xyzw: Any,
        frame_id: str,
    ) -> None:
        """One nav_msgs/msg/Path at `stamp_ns` holding every pose (see `path_fields`)."""
        self.write_raw(
            topic,
            "nav_msgs/msg/Path",
            path_cdr(stamp_ns, frame_id, stamps_ns, p_m, q_xyzw),
            stamp_ns,
        )

    def write_point_cloud(
        self, topic: str, stamp_ns: int, cloud: np.ndarray, frame_id: str
    ) -> None:
        """A sensor_msgs/msg/PointCloud2 of a structured array (see `point_cloud2_fields`)."""
        self.write(
            topic,
            "sensor_msgs/msg/PointCloud2",
            point_cloud2_fields(stamp_ns, frame_id, cloud),
            stamp_ns,
        )
