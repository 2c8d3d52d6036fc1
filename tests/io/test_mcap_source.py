"""MCAP in and out: independent writer/reader (rosbags), real rosbag2 file, damaged files."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from cvslam_cli.config import load_config
from cvslam_cli.errors import LogError
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.ros_messages import stamp_ns_of
from cvslam_cli.records.log import ImuSample, StereoFrame
from tests.synth import write_stereo_log

TS = get_typestore(Stores.ROS2_HUMBLE)


def _rosbags_log(bag_dir, n_frames=6, seed=3):
    """A rosbag2 (MCAP storage) written by rosbags: stereo mono8 + bgr8 images and IMU."""
    rng = np.random.default_rng(seed)
    Image, Imu = TS.types["sensor_msgs/msg/Image"], TS.types["sensor_msgs/msg/Imu"]
    Header, Time = TS.types["std_msgs/msg/Header"], TS.types["builtin_interfaces/msg/Time"]
    Vector3, Quat = TS.types["geometry_msgs/msg/Vector3"], TS.types["geometry_msgs/msg/Quaternion"]
    CameraInfo = TS.types["sensor_msgs/msg/CameraInfo"]
    ROI = TS.types["sensor_msgs/msg/RegionOfInterest"]
    written = {"left": [], "right": [], "imu": []}
    with Writer(bag_dir, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {
            "left": w.add_connection("/r1/stereo/left/image_raw", Image.__msgtype__, typestore=TS),
            "right": w.add_connection(
                "/r1/stereo/right/image_raw", Image.__msgtype__, typestore=TS
            ),
            "linfo": w.add_connection(
                "/r1/stereo/left/camera_info", CameraInfo.__msgtype__, typestore=TS
            ),
            "rinfo": w.add_connection(
                "/r1/stereo/right/camera_info", CameraInfo.__msgtype__, typestore=TS
            ),
            "imu": w.add_connection("/r1/imu", Imu.__msgtype__, typestore=TS),
        }
        for i in range(n_frames * 10):
            t = 5_000_000_000 + i * 5_000_000
            hdr = Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="r1/base_link")
            gyro, acc = rng.normal(size=3), rng.normal(size=3)
            msg = Imu(
                header=hdr,
                orientation=Quat(x=0, y=0, z=0, w=1),
                orientation_covariance=np.zeros(9),
                angular_velocity=Vector3(x=gyro[0], y=gyro[1], z=gyro[2]),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=Vector3(x=acc[0], y=acc[1], z=acc[2]),
                linear_acceleration_covariance=np.zeros(9),
            )
            w.write(conns["imu"], t, TS.serialize_cdr(msg, Imu.__msgtype__))
            written["imu"].append((t, gyro, acc))
            if i % 10:
                continue
            for side, enc in (("left", "mono8"), ("right", "bgr8")):
                shape = (30, 40) if enc == "mono8" else (30, 40, 3)
                img = rng.integers(0, 256, size=shape, dtype=np.uint8)
                frame = f"r1/{side}_optical"
                hdr = Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)
                msg = Image(
                    header=hdr,
                    height=30,
                    width=40,
                    encoding=enc,
                    is_bigendian=0,
                    step=40 * img.itemsize * (1 if img.ndim == 2 else 3),
                    data=img.reshape(-1),
                )
                w.write(conns[side], t, TS.serialize_cdr(msg, Image.__msgtype__))
                written[side].append((t, img))
                tx = -20.0 * 0.2 if side == "right" else 0.0
                info = CameraInfo(
                    header=hdr,
                    height=30,
                    width=40,
                    distortion_model="plumb_bob",
                    d=np.zeros(5),
                    k=np.array([20.0, 0, 20, 0, 20, 15, 0, 0, 1]),
                    r=np.eye(3).reshape(9),
                    p=np.array([20.0, 0, 20, tx, 0, 20, 15, 0, 0, 0, 1, 0]),
                    binning_x=0,
                    binning_y=0,
                    roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
                )
                w.write(
                    conns["linfo" if side == "left" else "rinfo"],
                    t,
                    TS.serialize_cdr(info, CameraInfo.__msgtype__),
                )
    (mcap_file,) = sorted(bag_dir.glob("*.mcap"))
    return mcap_file, written


def test_log_written_by_rosbags_reads_back_identically(tmp_path):
    mcap_file, written = _rosbags_log(tmp_path / "bag")
    logs = LogSet([McapLogSource(mcap_file)], load_config().logs)
    assert list(logs.vehicles) == ["r1"]
    recs = list(logs.records())
    frames = [r for r in recs if isinstance(r, StereoFrame)]
    imu = [r for r in recs if isinstance(r, ImuSample)]
    assert len(frames) == len(written["left"]) == 6
    for f, (lt, limg), (rt, rimg) in zip(frames, written["left"], written["right"], strict=True):
        assert f.stamp_ns == lt and f.right.stamp_ns == rt
        np.testing.assert_array_equal(f.left.image, limg)
        # bgr8 stays BGR
        np.testing.assert_array_equal(f.right.image, rimg)
    assert [s.stamp_ns for s in imu] == [t for t, _, _ in written["imu"]]
    for s, (_, gyro, acc) in zip(imu, written["imu"], strict=True):
        np.testing.assert_array_equal(s.gyro_rad_s, gyro)
        np.testing.assert_array_equal(s.accel_m_s2, acc)
    assert logs.rig("r1").baseline_m == pytest.approx(0.2)


def test_log_written_by_cvslam_reads_with_rosbags(tmp_path):
    synth = write_stereo_log(tmp_path / "ours.mcap", n_frames=4)
    with AnyReader([synth.path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types["/uav1/stereo/left/image_raw"] == "sensor_msgs/msg/Image"
        assert types["/uav1/stereo/left/camera_info"] == "sensor_msgs/msg/CameraInfo"
        assert types["/tf_static"] == "tf2_msgs/msg/TFMessage"
        lefts, imus = [], []
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/uav1/stereo/left/image_raw":
                lefts.append(msg)
            elif conn.topic == "/uav1/imu":
                imus.append(msg)
    assert len(lefts) == 4 and len(imus) == len(synth.imu)
    for msg, (stamp, img) in zip(lefts, synth.left, strict=True):
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
        np.testing.assert_array_equal(np.asarray(msg.data).reshape(48, 64), img)
    assert imus[0].angular_velocity.x == synth.imu[0][1][0]


def test_real_rosbag2_odometry(shared_data):
    path = shared_data / "ros2_odometry" / "nav2_turtlebot.mcap"
    cfg = load_config(
        overrides=["logs.vehicles.tb3.kind=ugv", "logs.vehicles.tb3.topics.odom=/odom"]
    ).logs
    logs = LogSet([McapLogSource(path)], cfg)
    odom = list(logs.records())
    assert len(odom) == 2639
    # stamps exactly as rosbags decodes them from the same file
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == "/odom"]
        ref = [
            stamp_ns_of(reader.deserialize(raw, c.msgtype))
            for c, _, raw in reader.messages(connections=conns)
        ]
    assert [r.stamp_ns for r in odom] == ref
    assert all(b > a for a, b in itertools.pairwise(ref))
    assert odom[0].frame_id == "odom" and odom[0].child_frame_id == "base_link"


def test_missing_file_directory_and_not_mcap(tmp_path):
    with pytest.raises(LogError, match="file not found"):
        McapLogSource(tmp_path / "nope.mcap")
    with pytest.raises(LogError, match="is a directory"):
        McapLogSource(tmp_path)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not mcap at all")
    with pytest.raises(LogError, match="not an MCAP file"):
        McapLogSource(bad)


def test_truncated_mid_chunk_reads_prefix_with_warning(tmp_path):
    synth = write_stereo_log(
        tmp_path / "full.mcap", n_frames=40, size=(160, 120), chunk_size=64 * 1024
    )
    data = synth.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    src = McapLogSource(cut)
    logs = LogSet([src], load_config().logs)
    frames = [r for r in logs.records() if isinstance(r, StereoFrame)]
    assert 10 < len(frames) < 40
    for f, (stamp, img) in zip(frames, synth.left, strict=False):
        assert f.stamp_ns == stamp
        np.testing.assert_array_equal(f.left.image, img)
    assert any("truncated" in w and "lost the messages logged" in w for w in src.warnings)
    assert any("truncated" in p.text for p in logs.problems)


def test_ros1_bag_converted_with_rosbags_reads(tmp_path):
    """The README's ROS 1 path: rosbags-convert to a ROS 2 MCAP, then read it."""
    import subprocess
    import sys
    from pathlib import Path

    from rosbags.rosbag1 import Writer as Ros1Writer

    ts1 = get_typestore(Stores.ROS1_NOETIC)
    Imu, Header = ts1.types["sensor_msgs/msg/Imu"], ts1.types["std_msgs/msg/Header"]
    Time, V3 = ts1.types["builtin_interfaces/msg/Time"], ts1.types["geometry_msgs/msg/Vector3"]
    Quat = ts1.types["geometry_msgs/msg/Quaternion"]
    with Ros1Writer(tmp_path / "in.bag") as w:
        conn = w.add_connection("/r/imu", Imu.__msgtype__, typestore=ts1)
        for i in range(20):
            t = 10**9 + i * 5_000_000
            msg = Imu(
                header=Header(seq=i, stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="r"),
                orientation=Quat(x=0, y=0, z=0, w=1),
                orientation_covariance=np.zeros(9),
                angular_velocity=V3(x=0.01 * i, y=0, z=0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=V3(x=0, y=0, z=9.81),
                linear_acceleration_covariance=np.zeros(9),
            )
            w.write(conn, t, ts1.serialize_ros1(msg, Imu.__msgtype__))
    convert = Path(sys.executable).with_name("rosbags-convert")
    subprocess.run(
        [
            str(convert),
            "--src",
            str(tmp_path / "in.bag"),
            "--dst",
            str(tmp_path / "out"),
            "--dst-storage",
            "mcap",
        ],
        check=True,
        capture_output=True,
    )
    (mcap_file,) = (tmp_path / "out").glob("*.mcap")
    logs = LogSet([McapLogSource(mcap_file)], load_config().logs)
    imu = list(logs.records())
    assert [s.stamp_ns for s in imu] == [10**9 + i * 5_000_000 for i in range(20)]
    assert imu[7].gyro_rad_s[0] == pytest.approx(0.07)


# -- damage: CRCs checked, reading on past it, losses named -----------------------------------


def _chunked_log(tmp_path):
    """A small log of several chunks and the byte offsets of its chunk records."""
    from mcap.reader import SeekingReader

    synth = write_stereo_log(tmp_path / "full.mcap", n_frames=8, chunk_size=8 * 1024)
    with synth.path.open("rb") as f:
        summary = SeekingReader(f).get_summary()
    chunks = sorted((ci.chunk_start_offset, ci.chunk_length) for ci in summary.chunk_indexes)
    return synth, bytearray(synth.path.read_bytes()), chunks


def _read(path):
    src = McapLogSource(path)
    logs = LogSet([src], load_config().logs, strict=False)
    recs = list(logs.records())
    return recs, src.warnings


def _frame_stamps(recs):
    return [r.stamp_ns for r in recs if isinstance(r, StereoFrame)]


def test_flipped_payload_bit_is_caught_by_the_chunk_crc_and_reading_goes_on(tmp_path):
    synth, data, chunks = _chunked_log(tmp_path)
    start, length = chunks[3]
    data[start + length // 2] ^= 0x10  # inside the compressed payload of chunk 3
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    recs, warnings = _read(bad)
    ref_recs, _ = _read(synth.path)
    (w,) = [w for w in warnings if "damaged MCAP" in w]
    assert f"bytes {start}-{start + length}" in w and "lost" in w and "/uav1/imu" in w
    # every record read is one of the original's, and those after the damage are there
    ref_frames = {r.stamp_ns: r for r in ref_recs if isinstance(r, StereoFrame)}
    stamps = _frame_stamps(recs)
    assert 0 < len(stamps) < len(ref_frames) and stamps[-1] == max(ref_frames)
    for r in recs:
        if isinstance(r, StereoFrame):
            np.testing.assert_array_equal(r.left.image, ref_frames[r.stamp_ns].left.image)


def test_truncated_log_with_a_damaged_chunk_reads_on_to_the_next_chunk(tmp_path):
    synth, data, chunks = _chunked_log(tmp_path)
    start, _ = chunks[2]
    data[start + 30 : start + 60] = bytes(30)  # the chunk's header and payload start
    cut = bytes(data[: chunks[-1][0] + 5])  # no summary: read front to back
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(cut)
    recs, warnings = _read(bad)
    assert any("no footer" in w for w in warnings)
    damaged = [w for w in warnings if "damaged MCAP" in w]
    assert len(damaged) == 2 and f"at bytes {start}-" in damaged[0]
    assert "lost 15 messages" in damaged[0] and "file truncated" in damaged[1]
    ref = _frame_stamps(_read(synth.path)[0])
    stamps = _frame_stamps(recs)
    assert set(stamps) < set(ref) and any(s > ref[3] for s in stamps)


def test_log_damaged_before_any_message_is_an_error_naming_the_damage(tmp_path):
    _, data, chunks = _chunked_log(tmp_path)
    for cut_at in (chunks[0][0] + 4, chunks[0][0] + chunks[0][1] // 2, 20):
        bad = tmp_path / f"cut{cut_at}.mcap"
        bad.write_bytes(bytes(data[:cut_at]))
        with pytest.raises(LogError, match=rf"{bad}: damaged MCAP.*no usable message"):
            _read(bad)


def test_damaged_summary_or_index_is_named_and_costs_no_message(tmp_path):
    synth, data, chunks = _chunked_log(tmp_path)
    ref, _ = _read(synth.path)
    summary = bytearray(data)
    summary[-200] ^= 0x01  # a chunk index in the summary
    index = bytearray(data)
    start, length = chunks[1]
    index[start + length + 30] ^= 0x01  # the message index records after chunk 1
    for variant, expected in ((summary, "summary section damaged"), (index, "message index")):
        bad = tmp_path / "bad.mcap"
        bad.write_bytes(bytes(variant))
        recs, warnings = _read(bad)
        assert any(expected in w for w in warnings), warnings
        assert _frame_stamps(recs) == _frame_stamps(ref)


def test_damage_outside_the_chunks_contents_is_named(tmp_path):
    """Flips the chunk CRCs cannot see are warnings too: a chunk header's time field (it
    disagrees with the chunk's content and index) and, where the writer stored the data
    section CRC, the file's Header record; every message read is intact."""
    from mcap.reader import SeekingReader
    from mcap_ros2.writer import Writer

    path = tmp_path / "a.mcap"
    with path.open("wb") as f:
        w = Writer(f, chunk_size=2048)
        w._writer._Writer__enable_data_crcs = True  # the library's option, off by default
        schema = w.register_msgdef("std_msgs/msg/String", "string data")
        for i in range(200):
            w.write_message("/t", schema, {"data": f"m{i:04d}"}, log_time=i, publish_time=i)
        w.finish()
    with path.open("rb") as f:
        reader = SeekingReader(f)
        chunks = sorted(c.chunk_start_offset for c in reader.get_summary().chunk_indexes)
        library = reader.get_header().library
    data = path.read_bytes()
    at_library = data.index(library.encode())
    for flip, expected in (
        (chunks[1] + 9 + 1, "the chunk disagrees with its header's time span"),
        (at_library, "data section CRC mismatch outside the message payloads"),
    ):
        bad = tmp_path / "bad.mcap"
        bad.write_bytes(data[:flip] + bytes([data[flip] ^ 0x01]) + data[flip + 1 :])
        src = McapLogSource(bad)
        assert [m.msg.data for m in src.messages()] == [f"m{i:04d}" for i in range(200)]
        assert any(expected in w for w in src.warnings), src.warnings
