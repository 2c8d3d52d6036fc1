"""Output files of `cvslam fuse`: map CSV/PLY, pose covariances, CSV tables, result.mcap."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.fuse_files import (
    MAP_COLUMNS,
    MAP_TOPIC,
    deadreckoning_path_topic,
    load_pose_covariances,
    path_topic,
    pose_topic,
    read_map_csv,
    save_pose_covariances,
    write_csv_atomic,
    write_map_csv,
    write_map_ply,
    write_result_mcap,
)
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.poses import PoseTable


def random_map(n: int = 40, seed: int = 0) -> LandmarkMap:
    rng = np.random.default_rng(seed)
    first = rng.integers(0, 10**10, n)
    names = ("uav1", "uav2", "ugv1", "uav1;uav2", "uav1;uav2;ugv1")
    return LandmarkMap(
        landmark_id=rng.permutation(10 * n)[:n].astype(np.int64),
        p_nav_m=rng.normal(scale=10.0 ** rng.uniform(-3, 4, (n, 1)), size=(n, 3)),
        std_m=np.abs(rng.normal(scale=0.5, size=(n, 3))),
        observers=tuple(str(names[k]) for k in rng.integers(0, len(names), n)),
        n_observations=rng.integers(1, 500, n),
        first_seen_ns=first,
        last_seen_ns=first + rng.integers(0, 10**9, n),
        in_state=rng.random(n) < 0.5,
        true_id=rng.integers(-2, 10 * n, n),
    )


def random_poses(n: int, seed: int, t0_ns: int = 1_000_000_000) -> PoseTable:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    stamps = t0_ns + np.cumsum(rng.integers(1, 50_000_000, n)).astype(np.int64)
    return PoseTable(stamps, rng.normal(scale=20.0, size=(n, 3)), q)


def assert_same_map(a: LandmarkMap, b: LandmarkMap) -> None:
    for name in (
        "landmark_id",
        "p_nav_m",
        "std_m",
        "n_observations",
        "first_seen_ns",
        "last_seen_ns",
        "in_state",
    ):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.observers == b.observers


# -- map.csv --------------------------------------------------------------------------------


def test_map_csv_round_trip_is_exact(tmp_path):
    table = random_map()
    path = tmp_path / "fuse" / "map.csv"
    write_map_csv(path, table)
    assert path.read_text().splitlines()[0] == ",".join(MAP_COLUMNS)
    assert_same_map(read_map_csv(path), table)
    assert not list(path.parent.glob("*.partial"))
    # pandas reads it too, with the expected dtypes
    frame = pd.read_csv(path)
    assert frame["in_state"].dtype == bool and frame["id"].dtype == np.int64
    np.testing.assert_array_equal(frame["x_m"].to_numpy(), table.p_nav_m[:, 0])


def test_empty_map_round_trips(tmp_path):
    empty = LandmarkMap(
        np.zeros(0, np.int64),
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        (),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, bool),
        np.zeros(0, np.int64),
    )
    write_map_csv(tmp_path / "map.csv", empty)
    back = read_map_csv(tmp_path / "map.csv")
    assert len(back) == 0 and back.p_nav_m.shape == (0, 3)
    write_map_ply(tmp_path / "map.ply", empty)
    header, data = parse_ply(tmp_path / "map.ply")
    assert "element vertex 0" in header and len(data) == 0


def test_map_csv_nan_std_round_trips(tmp_path):
    table = random_map(5, seed=1)
    std = table.std_m.copy()
    std[2, 1] = np.nan
    t2 = LandmarkMap(**{**vars(table), "std_m": std})
    write_map_csv(tmp_path / "m.csv", t2)
    back = read_map_csv(tmp_path / "m.csv")
    assert np.isnan(back.std_m[2, 1]) and np.isnan(back.std_m).sum() == 1


def test_map_csv_true_id_read_when_present_else_unknown(tmp_path):
    table = random_map(6, seed=4)
    path = tmp_path / "map.csv"
    write_map_csv(path, table)
    assert "true_id" not in path.read_text().splitlines()[0]
    np.testing.assert_array_equal(read_map_csv(path).true_id, np.full(6, -1))
    frame = pd.read_csv(path)
    frame["true_id"] = table.true_id
    frame.to_csv(path, index=False)
    back = read_map_csv(path)
    assert back.true_id.dtype == np.int64
    np.testing.assert_array_equal(back.true_id, table.true_id)


def _edit_csv(tmp_path, edit):
    path = tmp_path / "map.csv"
    write_map_csv(path, random_map(4, seed=3))
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")
    return path


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (
            lambda ls: [ls[0].replace(",std_y_m", ",sy"), *ls[1:]],
            "missing column(s) std_y_m",
        ),
        (
            lambda ls: [*ls[:2], ls[2].replace(",", ",x", 1), *ls[3:]],
            "line 3: column x_m: expected a number, got 'x",
        ),
        (
            lambda ls: [*ls[:3], "1.5" + ls[3][ls[3].index(",") :], *ls[4:]],
            "line 4: column id: expected an integer, got '1.5'",
        ),
        (
            lambda ls: [*ls[:4], ls[4].rsplit(",", 1)[0] + ",maybe"],
            "line 5: column in_state: expected True or False, got 'maybe'",
        ),
        (lambda ls: [*ls[:2], ls[2] + ",extra", *ls[3:]], "line 3: 13 fields, the header has 12"),
        (lambda ls: [], "empty file"),
        (
            lambda ls: [ls[0], ls[1], ls[1]],
            "not a usable map (LandmarkMap.landmark_id: id",
        ),
    ],
)
def test_map_csv_errors_are_one_line_naming_the_file(tmp_path, edit, expected):
    path = _edit_csv(tmp_path, edit)
    with pytest.raises(CvslamError) as err:
        read_map_csv(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(path)) and expected in msg, msg


def test_map_csv_missing_file(tmp_path):
    with pytest.raises(CvslamError, match=r"map\.csv: not found, expected a landmark map CSV"):
        read_map_csv(tmp_path / "map.csv")


# -- map.ply --------------------------------------------------------------------------------

_PLY_NUMPY = {"float": "<f4", "int": "<i4", "uint": "<u4", "double": "<f8", "uchar": "u1"}


def parse_ply(path):
    """A minimal independent PLY reader: (header text, structured vertex array)."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii")
    lines = header.splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count, props = None, []
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[0] == "property":
            props.append((words[2], _PLY_NUMPY[words[1]]))
    data = np.frombuffer(raw[end:], dtype=np.dtype(props))
    assert len(data) == count
    return header, data


def test_map_ply_parses_back(tmp_path):
    table = random_map(25, seed=5)
    path = tmp_path / "map.ply"
    write_map_ply(path, table)
    header, v = parse_ply(path)
    assert v.dtype.names == ("x", "y", "z", "id", "std", "n_obs")
    assert "property float x" in header and "property int id" in header
    np.testing.assert_array_equal(v["x"], table.p_nav_m[:, 0].astype(np.float32))
    np.testing.assert_array_equal(v["z"], table.p_nav_m[:, 2].astype(np.float32))
    np.testing.assert_array_equal(v["id"], table.landmark_id)
    np.testing.assert_array_equal(v["std"], table.std_m.max(axis=1).astype(np.float32))
    np.testing.assert_array_equal(v["n_obs"], table.n_observations)
    assert not list(tmp_path.glob("*.partial"))


def test_map_ply_refuses_ids_beyond_int32(tmp_path):
    table = random_map(3, seed=6)
    big = LandmarkMap(**{**vars(table), "landmark_id": np.array([1, 2, 2**40])})
    with pytest.raises(ValueError, match="int32"):
        write_map_ply(tmp_path / "map.ply", big)
    assert not list(tmp_path.iterdir())


# -- pose covariances ------------------------------------------------------------------------


def _covs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 6, 6))
    return np.arange(n, dtype=np.int64) * 50_000_000 + 7, A @ A.transpose(0, 2, 1)


def test_pose_covariances_round_trip_and_reproducible_bytes(tmp_path):
    stamps, cov = _covs(20, seed=7)
    a, b = tmp_path / "a" / "uav1_pose_cov.npz", tmp_path / "b.npz"
    save_pose_covariances(a, stamps, cov)
    save_pose_covariances(b, stamps, cov)
    assert a.read_bytes() == b.read_bytes()
    s2, c2 = load_pose_covariances(a)
    assert s2.dtype == np.int64 and c2.dtype == np.float64
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_array_equal(c2, cov)
    with np.load(a) as npz:
        assert str(npz["format"]) == "cvslam.pose_covariance" and int(npz["version"]) == 1
        assert list(npz["components"]) == [
            "x_m",
            "y_m",
            "z_m",
            "roll_rad",
            "pitch_rad",
            "yaw_rad",
        ]


def test_pose_covariances_refuse_other_versions_and_shapes(tmp_path):
    stamps, cov = _covs(3, seed=8)
    with pytest.raises(ValueError, match=r"cov: expected .* \(F, 6, 6\) = \(3, 6, 6\)"):
        save_pose_covariances(tmp_path / "x.npz", stamps, cov[:, :3, :3])
    path = tmp_path / "v2.npz"
    np.savez(path, format=np.array("cvslam.pose_covariance"), version=np.array(2))
    with pytest.raises(CvslamError) as err:
        load_pose_covariances(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and "version 2" in msg
    other = tmp_path / "other.npz"
    np.savez(other, stamps_ns=stamps)
    with pytest.raises(CvslamError, match="not a cvslam pose covariance file"):
        load_pose_covariances(other)
    corrupt = tmp_path / "corrupt.npz"
    np.savez(
        corrupt,
        format=np.array("cvslam.pose_covariance"),
        version=np.array(1),
        stamps_ns=stamps,
        cov=cov[:2],
    )
    with pytest.raises(CvslamError, match="corrupt pose covariance file"):
        load_pose_covariances(corrupt)
    with pytest.raises(CvslamError, match="not found"):
        load_pose_covariances(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(CvslamError, match="not a readable pose covariance file"):
        load_pose_covariances(tmp_path / "junk.npz")


# -- CSV tables -----------------------------------------------------------------------------


def test_write_csv_atomic_floats_read_back_exactly(tmp_path):
    rng = np.random.default_rng(9)
    x = rng.normal(size=500) * 10.0 ** rng.uniform(-300, 300, 500)
    frame = pd.DataFrame(
        {
            "stamp_ns": np.arange(500, dtype=np.int64) * 10**9,
            "vehicle": ["uav1", "ugv2"] * 250,
            "sigma_m": x,
            "nis": np.where(np.arange(500) % 7 == 0, np.nan, x),
        }
    )
    path = tmp_path / "fuse" / "timeline.csv"
    write_csv_atomic(path, frame)
    text = path.read_text()
    assert text.startswith("stamp_ns,vehicle,sigma_m,nis\n") and "\r" not in text
    back = pd.read_csv(path)
    np.testing.assert_array_equal(back["sigma_m"].to_numpy(), x)
    np.testing.assert_array_equal(back["nis"].to_numpy(), frame["nis"].to_numpy())
    np.testing.assert_array_equal(back["stamp_ns"].to_numpy(), frame["stamp_ns"].to_numpy())
    # exact with the standard library too (no pandas-specific parsing needed)
    rows = [line.split(",") for line in text.splitlines()[1:]]
    np.testing.assert_array_equal([float(r[2]) for r in rows], x)
    assert not list(path.parent.glob("*.partial"))


# -- result.mcap ----------------------------------------------------------------------------


def _result(tmp_path):
    trajectories = {"uav1": random_poses(12, seed=10), "ugv1": random_poses(7, seed=11)}
    dr = {"uav1": random_poses(12, seed=12)}
    landmarks = random_map(30, seed=13)
    path = tmp_path / "fuse" / "result.mcap"
    write_result_mcap(path, trajectories, landmarks, deadreckoning=dr, metadata={"filter": "nhinf"})
    return path, trajectories, dr, landmarks


def _cloud_array(msg) -> np.ndarray:
    types = {5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
    dtype = np.dtype(
        {
            "names": [f.name for f in msg.fields],
            "formats": [types[f.datatype] for f in msg.fields],
            "offsets": [f.offset for f in msg.fields],
            "itemsize": msg.point_step,
        }
    )
    return np.frombuffer(bytes(msg.data), dtype=dtype, count=msg.width * msg.height)


def _check_cloud(msg, landmarks: LandmarkMap) -> None:
    assert [f.name for f in msg.fields][:5] == ["x", "y", "z", "std", "id"]
    assert [f.datatype for f in msg.fields][:5] == [7, 7, 7, 7, 5]
    assert msg.is_dense and not msg.is_bigendian and msg.height == 1
    assert msg.width == len(landmarks) and msg.row_step == msg.point_step * msg.width
    cloud = _cloud_array(msg)
    np.testing.assert_array_equal(
        np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1),
        landmarks.p_nav_m.astype(np.float32),
    )
    np.testing.assert_array_equal(cloud["std"], landmarks.std_m.max(axis=1).astype(np.float32))
    np.testing.assert_array_equal(cloud["id"], landmarks.landmark_id)
    np.testing.assert_array_equal(cloud["n_obs"], landmarks.n_observations)


def _pose_arrays(poses) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    stamps = np.array([p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in poses])
    pos = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in poses])
    o = [p.pose.orientation for p in poses]
    return stamps, pos, np.array([[q.x, q.y, q.z, q.w] for q in o])


def test_result_mcap_reads_back_with_the_project_reader(tmp_path):
    path, trajectories, dr, landmarks = _result(tmp_path)
    assert not list(path.parent.glob("*.partial"))
    src = McapLogSource(path)
    topics = src.topics()
    assert topics[pose_topic("uav1")].schema_name == "geometry_msgs/msg/PoseStamped"
    assert topics[pose_topic("uav1")].message_count == 12
    assert topics[pose_topic("ugv1")].message_count == 7
    assert topics[path_topic("uav1")].schema_name == "nav_msgs/msg/Path"
    assert topics[path_topic("uav1")].message_count == 1
    assert topics[deadreckoning_path_topic("uav1")].message_count == 1
    assert deadreckoning_path_topic("ugv1") not in topics
    assert topics[MAP_TOPIC].schema_name == "sensor_msgs/msg/PointCloud2"
    md = src.metadata()["cvslam.fuse"]
    assert md["frame_id"] == "nav" and md["nav_frame"] == "NED" and md["filter"] == "nhinf"
    assert md["vehicles"] == "uav1;ugv1" and md["landmarks"] == "30"

    msgs: dict[str, list] = {}
    for m in src.messages():
        msgs.setdefault(m.topic, []).append(m)
    for vehicle, table in trajectories.items():
        poses = msgs[pose_topic(vehicle)]
        stamps, pos, q = _pose_arrays([m.msg for m in poses])
        np.testing.assert_array_equal(stamps, table.stamps_ns)
        np.testing.assert_array_equal([m.log_time_ns for m in poses], table.stamps_ns)
        np.testing.assert_array_equal(pos, table.p_nav_m)
        np.testing.assert_array_equal(q, table.q_nav_body_xyzw)
        assert all(m.msg.header.frame_id == "nav" for m in poses)
        (path_msg,) = msgs[path_topic(vehicle)]
        assert path_msg.log_time_ns == table.stamps_ns[-1]
        assert len(path_msg.msg.poses) == len(table)
        stamps, pos, q = _pose_arrays(path_msg.msg.poses)
        np.testing.assert_array_equal(stamps, table.stamps_ns)
        np.testing.assert_array_equal(pos, table.p_nav_m)
        np.testing.assert_array_equal(q, table.q_nav_body_xyzw)
    (dr_msg,) = msgs[deadreckoning_path_topic("uav1")]
    np.testing.assert_array_equal(_pose_arrays(dr_msg.msg.poses)[1], dr["uav1"].p_nav_m)
    (cloud_msg,) = msgs[MAP_TOPIC]
    last = max(int(t.stamps_ns[-1]) for t in (*trajectories.values(), *dr.values()))
    assert cloud_msg.log_time_ns == last
    _check_cloud(cloud_msg.msg, landmarks)


def test_result_mcap_opens_with_rosbags(tmp_path):
    rosbags_highlevel = pytest.importorskip("rosbags.highlevel")
    path, trajectories, _, landmarks = _result(tmp_path)
    with rosbags_highlevel.AnyReader([path]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts[pose_topic("uav1")] == 12 and counts[MAP_TOPIC] == 1
        by_topic = {c.topic: c for c in reader.connections}
        conn = by_topic[path_topic("ugv1")]
        _, _, raw = next(iter(reader.messages(connections=[conn])))
        msg = reader.deserialize(raw, conn.msgtype)
        np.testing.assert_array_equal(_pose_arrays(msg.poses)[1], trajectories["ugv1"].p_nav_m)
        conn = by_topic[MAP_TOPIC]
        _, _, raw = next(iter(reader.messages(connections=[conn])))
        _check_cloud(reader.deserialize(raw, conn.msgtype), landmarks)


def test_result_mcap_rejects_bad_vehicle_names_and_leaves_nothing(tmp_path):
    path = tmp_path / "result.mcap"
    with pytest.raises(CvslamError, match="vehicle name 'uav 1'"):
        write_result_mcap(path, {"uav 1": random_poses(3, seed=14)}, random_map(2))
    assert not list(tmp_path.iterdir())


def test_result_mcap_with_only_a_map(tmp_path):
    path = tmp_path / "result.mcap"
    landmarks = random_map(4, seed=15)
    write_result_mcap(path, {}, landmarks)
    (m,) = list(McapLogSource(path).messages())
    assert m.topic == MAP_TOPIC and m.log_time_ns == landmarks.last_seen_ns.max()
    _check_cloud(m.msg, landmarks)
