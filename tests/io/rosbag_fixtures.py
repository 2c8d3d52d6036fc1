"""Bags written by `rosbags` (an independent writer) from the real EuRoC clip.

`euroc_messages` reads the clip's first stereo pairs (PNG), CameraInfo from each camera's
`sensor.yaml` (radial-tangential -> plumb_bob, R = I, P = [K | 0]) and the IMU samples of the
same window, as (topic, log time ns, ROS message type, field values) in log-time order;
`write_rosbag2` / `write_ros1` write them with rosbags' own message classes and serialisers.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

ROS2 = get_typestore(Stores.ROS2_HUMBLE)
ROS1 = get_typestore(Stores.ROS1_NOETIC)
if "tf2_msgs/msg/TFMessage" not in ROS1.fielddefs:  # not in rosbags' Noetic store
    ROS1.register(
        get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
    )


@dataclass(frozen=True)
class Topics:
    """Topic names of one vehicle's bag."""

    left: str = "/uav1/stereo/left/image_raw"
    right: str = "/uav1/stereo/right/image_raw"
    left_info: str = "/uav1/stereo/left/camera_info"
    right_info: str = "/uav1/stereo/right/camera_info"
    imu: str = "/uav1/imu"


EUROC_TOPICS = Topics(
    "/cam0/image_raw", "/cam1/image_raw", "/cam0/camera_info", "/cam1/camera_info", "/imu0"
)


@dataclass(frozen=True)
class Item:
    topic: str
    log_time_ns: int
    msgtype: str
    fields: dict[str, Any]


def _camera_fields(sensor_yaml: Path) -> dict[str, Any]:
    text = sensor_yaml.read_text().replace("%YAML:1.0", "")
    d = yaml.safe_load(text)
    fx, fy, cx, cy = d["intrinsics"]
    K = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=float)
    P = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=float)
    w, h = d["resolution"]
    return {
        "height": h,
        "width": w,
        "distortion_model": "plumb_bob",
        "d": np.array([*d["distortion_coefficients"], 0.0], dtype=float),
        "k": K,
        "r": np.eye(3).ravel(),
        "p": P,
    }


def _T_BS(sensor_yaml: Path) -> np.ndarray:
    d = yaml.safe_load(sensor_yaml.read_text().replace("%YAML:1.0", ""))
    return np.array(d["T_BS"]["data"], dtype=float).reshape(4, 4)


def euroc_messages(
    mav0: Path, n_pairs: int, topics: Topics = Topics(), *, camera_info: bool = True
) -> list[Item]:
    """The clip's first `n_pairs` stereo pairs, one CameraInfo per camera with the first
    pair, and its IMU samples up to the last pair, in log-time order."""
    stamps = [
        int(line.split(",")[0])
        for line in (mav0 / "cam0/data.csv").read_text().split("\n")[1:]
        if line.strip()
    ][:n_pairs]
    items: list[Item] = [
        Item(
            "/tf_static",
            stamps[0],
            "tf2_msgs/msg/TFMessage",
            {
                "transforms": [
                    (f"uav1/{cam}", _T_BS(mav0 / cam / "sensor.yaml")) for cam in ("cam0", "cam1")
                ],
                "stamp": stamps[0],
            },
        )
    ]
    if not camera_info:  # neither CameraInfo nor /tf_static: the calibration is the config's
        items = []
    for side, cam, topic, info in (
        ("left", "cam0", topics.left, topics.left_info),
        ("right", "cam1", topics.right, topics.right_info),
    ):
        frame = f"uav1/{cam}"
        info_fields = _camera_fields(mav0 / cam / "sensor.yaml")
        if camera_info:
            items.append(
                Item(
                    info,
                    stamps[0],
                    "sensor_msgs/msg/CameraInfo",
                    {"stamp": stamps[0], "frame_id": frame, **info_fields},
                )
            )
        for st in stamps:
            img = cv2.imread(str(mav0 / cam / "data" / f"{st}.png"), cv2.IMREAD_GRAYSCALE)
            h, w = img.shape
            items.append(
                Item(
                    topic,
                    st,
                    "sensor_msgs/msg/Image",
                    {
                        "stamp": st,
                        "frame_id": frame,
                        "height": h,
                        "width": w,
                        "encoding": "mono8",
                        "is_bigendian": 0,
                        "step": w,
                        "data": img.reshape(-1),
                    },
                )
            )
        del side
    for line in (mav0 / "imu0/data.csv").read_text().split("\n")[1:]:
        if not line.strip():
            continue
        v = [float(x) for x in line.split(",")]
        st = int(line.split(",")[0])
        if st > stamps[-1]:
            break
        items.append(
            Item(
                topics.imu,
                st,
                "sensor_msgs/msg/Imu",
                {"stamp": st, "frame_id": "uav1/base_link", "gyro": v[1:4], "accel": v[4:7]},
            )
        )
    items.sort(key=lambda i: i.log_time_ns)
    return items


def _tf_message(store: Any, item: Item) -> Any:
    """tf2_msgs/TFMessage: uav1/base_link -> each (child, T_parent_child)."""
    from scipy.spatial.transform import Rotation

    T = store.types
    st = item.fields["stamp"]
    out = []
    for child, M in item.fields["transforms"]:
        x, y, z, w = Rotation.from_matrix(M[:3, :3]).as_quat()
        hkw: dict[str, Any] = {
            "stamp": T["builtin_interfaces/msg/Time"](sec=st // 10**9, nanosec=st % 10**9),
            "frame_id": "uav1/base_link",
        }
        if store is ROS1:
            hkw["seq"] = 0
        tr = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](*M[:3, 3]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        )
        out.append(
            T["geometry_msgs/msg/TransformStamped"](
                header=T["std_msgs/msg/Header"](**hkw), child_frame_id=child, transform=tr
            )
        )
    return T["tf2_msgs/msg/TFMessage"](transforms=out)


def _message(store: Any, item: Item) -> Any:
    if item.msgtype == "tf2_msgs/msg/TFMessage":
        return _tf_message(store, item)
    T = store.types
    f = dict(item.fields)
    st = f.pop("stamp")
    stamp = T["builtin_interfaces/msg/Time"](sec=st // 10**9, nanosec=st % 10**9)
    header_kw: dict[str, Any] = {"stamp": stamp, "frame_id": f.pop("frame_id")}
    if store is ROS1:
        header_kw["seq"] = 0
    header = T["std_msgs/msg/Header"](**header_kw)
    cls = T[item.msgtype]
    if item.msgtype == "sensor_msgs/msg/Imu":
        V3 = T["geometry_msgs/msg/Vector3"]
        Q = T["geometry_msgs/msg/Quaternion"]
        cov = np.zeros(9)
        return cls(
            header=header,
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.r_[-1.0, np.zeros(8)],
            angular_velocity=V3(*f["gyro"]),
            angular_velocity_covariance=cov,
            linear_acceleration=V3(*f["accel"]),
            linear_acceleration_covariance=cov,
        )
    if item.msgtype == "sensor_msgs/msg/CameraInfo":
        roi = T["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False)
        if store is ROS1:  # ROS 1's field names
            f = {(k.upper() if k in "dkrp" else k): v for k, v in f.items()}
        return cls(header=header, binning_x=0, binning_y=0, roi=roi, **f)
    return cls(header=header, **f)


def write_rosbag2(
    items: list[Item], out: Path, storage: str = "mcap", compression: str = "none"
) -> Path:
    """A rosbag2 folder (`storage` mcap or sqlite3; `compression` none, file or message)."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    w = Writer2(out, version=9, storage_plugin=plugin)
    if compression != "none":
        mode = CompressionMode.FILE if compression == "file" else CompressionMode.MESSAGE
        w.set_compression(mode, CompressionFormat.ZSTD)
    with w:
        _write_all(w, items, ROS2, ROS2.serialize_cdr)
    return out


def _write_all(w: Any, items: list[Item], store: Any, serialize: Any) -> None:
    """Every item through writer `w`, one connection per topic, serialised by `serialize`."""
    conns: dict[str, Any] = {}
    for it in items:
        if it.topic not in conns:
            conns[it.topic] = w.add_connection(it.topic, it.msgtype, typestore=store)
        w.write(conns[it.topic], it.log_time_ns, serialize(_message(store, it), it.msgtype))


def write_split_rosbag2(items: list[Item], out: Path, tmp: Path) -> Path:
    """A rosbag2 MCAP folder split in two files at the middle message (what `ros2 bag record
    --max-bag-size` leaves): two bags written, their files and metadata joined."""
    half = len(items) // 2
    parts = [write_rosbag2(items[:half], tmp / "part0"), write_rosbag2(items[half:], tmp / "part1")]
    out.mkdir()
    metas = []
    for i, part in enumerate(parts):
        (src,) = part.glob("*.mcap")
        shutil.copy(src, out / f"{out.name}_{i}.mcap")
        metas.append(yaml.safe_load((part / "metadata.yaml").read_text()))
    info = metas[0]["rosbag2_bagfile_information"]
    second = metas[1]["rosbag2_bagfile_information"]
    start = info["starting_time"]["nanoseconds_since_epoch"]
    end = second["starting_time"]["nanoseconds_since_epoch"] + second["duration"]["nanoseconds"]
    counts: dict[str, dict[str, Any]] = {}
    for m in (info, second):
        for t in m["topics_with_message_count"]:
            name = t["topic_metadata"]["name"]
            if name in counts:
                counts[name]["message_count"] += t["message_count"]
            else:
                counts[name] = dict(t)
    info["relative_file_paths"] = [f"{out.name}_0.mcap", f"{out.name}_1.mcap"]
    info["duration"]["nanoseconds"] = end - start
    info["message_count"] = info["message_count"] + second["message_count"]
    info["topics_with_message_count"] = list(counts.values())
    info["files"] = [
        {**f, "path": f"{out.name}_{i}.mcap"}
        for i, m in enumerate(metas)
        for f in m["rosbag2_bagfile_information"]["files"]
    ]
    (out / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))
    return out


def write_ros1(items: list[Item], out: Path) -> Path:
    """A ROS 1 bag (ROS 1 Noetic definitions: CameraInfo's D K R P, the header's seq)."""
    with Writer1(out) as w:
        _write_all(w, items, ROS1, ROS1.serialize_ros1)
    return out


def only_file(folder: Path, pattern: str) -> Path:
    (path,) = folder.glob(pattern)
    return path


def iter_topics(items: list[Item]) -> Iterator[str]:
    seen: list[str] = []
    for it in items:
        if it.topic not in seen:
            seen.append(it.topic)
            yield it.topic
