"""`result.mcap`, the viewer log: read back with the `mcap` library (and mcap-ros2-support's
decoder) and with `rosbags`, independently of the project's reader: schemas, message time
spans (poses and paths spread over the run, the map growing), the tf tree (nav -> vehicles,
enu -> nav, body -> cameras), ground truth, covariances, and the size bounds."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.rotations import make_T, quat_xyzw_to_matrix
from cvslam_cli.io.result_mcap import (
    MAP_TOPIC,
    ResultDecimation,
    deadreckoning_path_topic,
    ground_truth_path_topic,
    path_topic,
    pose_topic,
    snapshot_times,
    thinned,
    write_result_mcap,
)
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.poses import PoseTable
from tests.io.test_fuse_files import random_map

S = 1_000_000_000
T0 = 5 * S


def poses(n: int, seed: int, t0_ns: int = T0, dt_ns: int = 100_000_000) -> PoseTable:
    """n random poses `dt_ns` apart from `t0_ns`."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    stamps = t0_ns + dt_ns * np.arange(n, dtype=np.int64)
    return PoseTable(stamps, rng.normal(scale=20.0, size=(n, 3)), q)


def covariances(n: int, seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(n, 6, 6))
    return a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(6)


def rig(baseline_m: float) -> StereoRig:
    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    R_body_cam = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])  # forward-looking
    left = CameraModel(640, 480, K, T_body_cam=make_T(R_body_cam, [0.2, 0.0, 0.1]))
    right = CameraModel(640, 480, K, T_body_cam=make_T(R_body_cam, [0.2, baseline_m, 0.1]))
    return StereoRig(left, right)


def growing_map(n: int, seed: int) -> LandmarkMap:
    """`random_map` with first observations spread over 5..10 s."""
    m = random_map(n, seed)
    first = np.random.default_rng(seed).integers(T0, T0 + 5 * S, n)
    return LandmarkMap(
        m.landmark_id,
        m.p_nav_m,
        m.std_m,
        m.observers,
        m.n_observations,
        first,
        first + 1000,
        m.in_state,
        m.true_id,
    )


class Written:
    """A result.mcap of two vehicles over 5 s (uav1 50 poses, ugv1 20 from 6 s on), dead
    reckoning and ground truth for uav1, both rigs, a map growing over the 5 s."""

    def __init__(self, tmp_path: Path, decimation: ResultDecimation | None = None):
        self.est = {"uav1": poses(50, 1), "ugv1": poses(20, 2, t0_ns=T0 + S, dt_ns=200_000_000)}
        self.cov = {"uav1": covariances(50, 3), "ugv1": covariances(20, 4)}
        self.dr = {"uav1": poses(50, 5)}
        self.gt = {"uav1": poses(250, 6, t0_ns=T0 - S // 2, dt_ns=20_000_000)}
        self.rigs = {"uav1": rig(0.5), "ugv1": rig(0.3)}
        self.landmarks = growing_map(60, 7)
        self.path = tmp_path / "fuse" / "result.mcap"
        write_result_mcap(
            self.path,
            self.est,
            self.landmarks,
            pose_covariances=self.cov,
            deadreckoning=self.dr,
            ground_truth=self.gt,
            rigs=self.rigs,
            metadata={"filter": "hinf"},
            decimation=decimation or ResultDecimation(),
        )


def read_mcap(path: Path) -> tuple[dict[str, list], dict[str, str], dict[str, dict[str, str]]]:
    """({topic: [(log_time_ns, message)]}, {topic: schema name}, metadata) with the mcap
    library; checks the encodings on the way."""
    msgs: dict[str, list] = defaultdict(list)
    schemas: dict[str, str] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            schemas[channel.topic] = schema.name
            msgs[channel.topic].append((message.log_time, decoded))
        f.seek(0)
        metadata = {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
    return msgs, schemas, metadata


def stamp(h) -> int:
    return h.stamp.sec * S + h.stamp.nanosec


def pose_rows(msgs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps, positions, quaternions xyzw) of PoseStamped messages."""
    st = np.array([stamp(m.header) for m in msgs], dtype=np.int64)
    p = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z] for m in msgs])
    q = np.array([[o.x, o.y, o.z, o.w] for o in (m.pose.orientation for m in msgs)])
    return st, p.reshape(-1, 3), q.reshape(-1, 4)


def cloud_ids(msg) -> np.ndarray:
    field = {f.name: f for f in msg.fields}["id"]
    assert field.datatype == 5 and msg.height == 1 and not msg.is_bigendian
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(msg.width, msg.point_step)
    return data[:, field.offset : field.offset + 4].copy().view("<i4").reshape(-1)


def transform_matrix(tr) -> np.ndarray:
    t, r = tr.translation, tr.rotation
    return make_T(quat_xyzw_to_matrix(np.array([r.x, r.y, r.z, r.w])), [t.x, t.y, t.z])


EXPECTED_SCHEMAS = {
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/uav1/fuse/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/ugv1/fuse/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "/uav1/fuse/path": "nav_msgs/msg/Path",
    "/ugv1/fuse/path": "nav_msgs/msg/Path",
    "/uav1/deadreckoning/path": "nav_msgs/msg/Path",
    "/uav1/ground_truth/path": "nav_msgs/msg/Path",
    "/map/landmarks": "sensor_msgs/msg/PointCloud2",
}


@pytest.fixture
def written(tmp_path) -> Written:
    return Written(tmp_path)


def test_schemas_and_metadata(written):
    _, schemas, metadata = read_mcap(written.path)
    assert schemas == EXPECTED_SCHEMAS
    md = metadata["cvslam.fuse"]
    assert (md["frame_id"], md["nav_frame"], md["display_frame"]) == ("nav", "NED", "enu")
    assert md["vehicles"] == "uav1;ugv1" and md["landmarks"] == "60" and md["filter"] == "hinf"
    assert not list(written.path.parent.glob("*.partial"))


def test_poses_one_per_estimate_at_its_own_stamp_with_covariance(written):
    msgs, _, _ = read_mcap(written.path)
    for v, table in written.est.items():
        got = msgs[pose_topic(v)]
        log_times = np.array([t for t, _ in got])
        np.testing.assert_array_equal(log_times, table.stamps_ns)
        st, p, q = pose_rows([m.pose and _Stamped(m) for _, m in got])
        np.testing.assert_array_equal(st, table.stamps_ns)
        np.testing.assert_array_equal(p, table.p_nav_m)
        np.testing.assert_array_equal(q, table.q_nav_body_xyzw)
        cov = np.array([np.reshape(m.pose.covariance, (6, 6)) for _, m in got])
        np.testing.assert_array_equal(cov, written.cov[v])
        assert {m.header.frame_id for _, m in got} == {"nav"}


class _Stamped:
    """A PoseWithCovarianceStamped seen as a PoseStamped (header, pose)."""

    def __init__(self, m) -> None:
        self.header, self.pose = m.header, m.pose.pose


def test_paths_grow_over_the_run_and_end_complete(written):
    msgs, _, _ = read_mcap(written.path)
    tables = {
        path_topic("uav1"): written.est["uav1"],
        path_topic("ugv1"): written.est["ugv1"],
        deadreckoning_path_topic("uav1"): written.dr["uav1"],
        ground_truth_path_topic("uav1"): written.gt["uav1"],
    }
    for topic, table in tables.items():
        got = msgs[topic]
        times = np.array([t for t, _ in got])
        sizes = [len(m.poses) for _, m in got]
        span_s = (table.stamps_ns[-1] - table.stamps_ns[0]) / S
        # about one a second, spread over the run (not all at the end)
        assert len(got) >= int(span_s) and np.all(np.diff(times) > 0), topic
        assert times[0] <= table.stamps_ns[0] + S and times[-1] == table.stamps_ns[-1], topic
        assert np.all(np.diff(sizes) > 0), topic
        for t, m in got:
            assert stamp(m.header) == t and m.header.frame_id == "nav"
            st, p, _ = pose_rows(m.poses)
            upto = table.stamps_ns <= t
            np.testing.assert_array_equal(st, table.stamps_ns[upto])  # all: fewer than 1000
            np.testing.assert_array_equal(p, table.p_nav_m[upto])


def test_map_grows_with_the_landmarks_first_seen(written):
    msgs, _, _ = read_mcap(written.path)
    got = msgs[MAP_TOPIC]
    lm = written.landmarks
    assert len(got) >= 5
    last_pose = max(int(t.stamps_ns[-1]) for t in (*written.est.values(), *written.dr.values()))
    assert got[-1][0] == last_pose
    sizes = [m.width for _, m in got]
    assert np.all(np.diff(sizes) > 0) and sizes[-1] == len(lm)
    for k, (t, m) in enumerate(got):
        assert stamp(m.header) == t and m.header.frame_id == "nav"
        # the last one holds the whole map (every landmark, at the end of the run)
        expected = lm.landmark_id if k == len(got) - 1 else lm.landmark_id[lm.first_seen_ns <= t]
        np.testing.assert_array_equal(np.sort(cloud_ids(m)), np.sort(expected))


def test_tf_tree(written):
    msgs, _, _ = read_mcap(written.path)
    ((t_static, static),) = msgs["/tf_static"]
    first = min(int(t.stamps_ns[0]) for t in (*written.est.values(), *written.gt.values()))
    assert t_static == first
    edges = {
        (x.header.frame_id, x.child_frame_id): transform_matrix(x.transform)
        for x in static.transforms
    }
    # ENU beside NED: x east = nav y, y north = nav x, z up = -nav z
    T_enu_nav = edges[("enu", "nav")]
    np.testing.assert_allclose(T_enu_nav @ [1.0, 2.0, 3.0, 1.0], [2.0, 1.0, -3.0, 1.0])
    for v, r in written.rigs.items():
        np.testing.assert_allclose(
            edges[(f"{v}/base_link", f"{v}/left_camera_optical")], r.left.T_body_cam, atol=1e-12
        )
        np.testing.assert_allclose(
            edges[(f"{v}/base_link", f"{v}/right_camera_optical")], r.right.T_body_cam, atol=1e-12
        )
    assert len(edges) == 5
    by_child: dict[str, list] = defaultdict(list)
    for t, m in msgs["/tf"]:
        for x in m.transforms:
            assert x.header.frame_id == "nav" and stamp(x.header) == t
            by_child[x.child_frame_id].append((t, transform_matrix(x.transform)))
    assert set(by_child) == {"uav1/base_link", "ugv1/base_link"}
    for v, table in written.est.items():
        got = by_child[f"{v}/base_link"]
        np.testing.assert_array_equal([t for t, _ in got], table.stamps_ns)
        R = quat_xyzw_to_matrix(table.q_nav_body_xyzw)
        for (_, T), Rk, pk in zip(got, R, table.p_nav_m, strict=True):
            np.testing.assert_allclose(T, make_T(Rk, pk), atol=1e-12)


def test_reads_back_with_rosbags(written):
    rosbags_highlevel = pytest.importorskip("rosbags.highlevel")
    msgs, _, _ = read_mcap(written.path)
    with rosbags_highlevel.AnyReader([written.path]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == EXPECTED_SCHEMAS
        counts: dict[str, int] = defaultdict(int)
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
            if conn.topic == pose_topic("uav1") and counts[conn.topic] == 7:
                assert t == written.est["uav1"].stamps_ns[6] == stamp(msg.header)
                np.testing.assert_array_equal(
                    msg.pose.covariance.reshape(6, 6), written.cov["uav1"][6]
                )
            if conn.topic == MAP_TOPIC:
                assert msg.width == int(np.sum(written.landmarks.first_seen_ns <= t)) or (
                    t == msgs[MAP_TOPIC][-1][0] and msg.width == len(written.landmarks)
                )
            if conn.topic == "/tf_static":
                assert {x.child_frame_id for x in msg.transforms} >= {
                    "nav",
                    "uav1/left_camera_optical",
                }
        assert dict(counts) == {k: len(v) for k, v in msgs.items()}


def test_decimation_bounds_the_file(tmp_path):
    d = ResultDecimation(period_ns=S // 10, max_messages=4, max_path_poses=5, max_map_points=180)
    written = Written(tmp_path, d)
    msgs, _, _ = read_mcap(written.path)
    for topic in (path_topic("uav1"), ground_truth_path_topic("uav1"), MAP_TOPIC):
        assert 2 <= len(msgs[topic]) <= 4 + 1, topic  # the snapshots and the final message
    for _, m in msgs[ground_truth_path_topic("uav1")]:
        assert len(m.poses) <= 5
    _, last = msgs[ground_truth_path_topic("uav1")][-1]
    st, _, _ = pose_rows(last.poses)
    gt = written.gt["uav1"].stamps_ns
    assert st[0] == gt[0] and st[-1] == gt[-1]  # thinned, first and last kept
    assert sum(m.width for _, m in msgs[MAP_TOPIC]) <= 180
    assert msgs[MAP_TOPIC][-1][1].width == len(written.landmarks)
    # poses are never thinned: one per estimate
    assert len(msgs[pose_topic("uav1")]) == 50


def test_snapshot_times_and_thinning():
    np.testing.assert_array_equal(snapshot_times(10, 35, 10, 100), [10, 20, 30])
    np.testing.assert_array_equal(snapshot_times(0, 1000, 10, 4), [0, 250, 500, 750])
    assert len(snapshot_times(5, 5, 10, 4)) == 0
    np.testing.assert_array_equal(thinned(4, 10), [0, 1, 2, 3])
    idx = thinned(101, 5)
    np.testing.assert_array_equal(idx, [0, 25, 50, 75, 100])


def test_rejects_bad_vehicle_names_and_leaves_nothing(tmp_path):
    path = tmp_path / "result.mcap"
    with pytest.raises(CvslamError, match="vehicle name 'uav 1'"):
        write_result_mcap(path, {"uav 1": poses(3, seed=14)}, random_map(2))
    assert not list(tmp_path.iterdir())


def test_only_a_map(tmp_path):
    path = tmp_path / "result.mcap"
    landmarks = random_map(4, seed=15)
    write_result_mcap(path, {}, landmarks)
    msgs, _, _ = read_mcap(path)
    ((t, cloud),) = msgs[MAP_TOPIC]
    assert t == landmarks.last_seen_ns.max() and cloud.width == 4
    ((_, static),) = msgs["/tf_static"]
    assert [(x.header.frame_id, x.child_frame_id) for x in static.transforms] == [("enu", "nav")]


def test_the_fuse_stage_writes_truth_rigs_and_covariances(small_image_run):
    """The real stage's result.mcap (simulated run with ground truth)."""
    msgs, schemas, _ = read_mcap(small_image_run / "fuse" / "result.mcap")
    for v in ("uav1", "uav2"):
        assert schemas[ground_truth_path_topic(v)] == "nav_msgs/msg/Path"
        covs = [np.reshape(m.pose.covariance, (6, 6)) for _, m in msgs[pose_topic(v)]]
        assert all(np.all(np.linalg.eigvalsh(c) > 0) for c in covs)
        assert len(msgs[path_topic(v)]) >= 7  # an 8 s run
    ((_, static),) = msgs["/tf_static"]
    children = {x.child_frame_id for x in static.transforms}
    assert children == {
        "nav",
        *(f"{v}/{s}_camera_optical" for v in ("uav1", "uav2") for s in ("left", "right")),
    }


def test_the_foxglove_layout_in_docs_names_topics_and_frames_a_run_has(small_image_run):
    """docs/foxglove_layout.json (two UAVs, the demo's names) against a two-UAV run."""
    import json

    layout = json.loads((Path(__file__).parents[2] / "docs" / "foxglove_layout.json").read_text())
    msgs, schemas, _ = read_mcap(small_image_run / "fuse" / "result.mcap")
    panel = layout["configById"]["3D!cvslam"]
    assert panel["followTf"] == "enu" and set(panel["topics"]) <= set(schemas)
    frames = {"nav", "enu"} | {
        x.child_frame_id for t in ("/tf", "/tf_static") for _, m in msgs[t] for x in m.transforms
    }
    assert {k.removeprefix("frame:") for k in panel["transforms"]} <= frames
    plotted = {p["value"].split(".")[0] for p in layout["configById"]["Plot!cvslam"]["paths"]}
    assert plotted <= set(schemas)
    assert set(layout["layout"].values()) >= {"3D!cvslam", "Plot!cvslam"}
