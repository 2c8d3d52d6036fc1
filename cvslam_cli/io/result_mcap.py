"""`result.mcap`: the fuse results as a ROS 2 log a viewer plays (Foxglove, `ros2 bag play`,
rosbags; docs/viewers.md, docs/fuse_outputs.md).

Everything grows over time, each message stamped (header and log time) at the time it
describes, so that playback shows the run as it happened:
- per estimated pose: `/tf` nav -> `<v>/base_link` and `/<v>/fuse/pose`
  (geometry_msgs/PoseWithCovarianceStamped, the 6x6 pose covariance);
- about once a second (`ResultDecimation`): `/<v>/fuse/path`, `/<v>/deadreckoning/path`,
  `/<v>/ground_truth/path` (nav_msgs/Path of the poses up to then) and `/map/landmarks`
  (sensor_msgs/PointCloud2 of the landmarks first seen by then, at their final positions);
  each topic also gets a last message at its last stamp, holding everything;
- `/tf_static` once, at the first stamp: `enu` -> `nav` (a z-up frame beside the NED nav
  frame, for z-up viewers) and `<v>/base_link` -> each camera's optical frame (the rig).

The file stays bounded for long runs: a growing topic gets at most `max_messages` messages
(the period is stretched), a Path at most `max_path_poses` poses (evenly thinned, the first
and last kept), and the map clouds at most `max_map_points` points over all messages.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.geometry.output_frames import T_ENU_NAV
from cvslam_cli.geometry.rotations import make_T, quat_xyzw_to_matrix
from cvslam_cli.io.fuse_files import OBSERVER_SEPARATOR, map_vertices
from cvslam_cli.io.mcap_writer import (
    LogWriter,
    path_cdr,
    point_cloud2_fields,
    pose_with_covariance_fields,
    tf_message_fields,
)
from cvslam_cli.io.names import NAV_FRAME_ID, TF_STATIC_TOPIC, vehicle_names
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.poses import PoseTable

MAP_TOPIC = "/map/landmarks"
_CLOUD = "sensor_msgs/msg/PointCloud2"
TF_TOPIC = "/tf"
ENU_FRAME_ID = "enu"
RESULT_METADATA_NAME = "cvslam.fuse"
CLOUD_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("std", "<f4"), ("id", "<i4"), ("n_obs", "<i4")]
)


def pose_topic(vehicle: str) -> str:
    return f"/{vehicle}/fuse/pose"


def path_topic(vehicle: str) -> str:
    return f"/{vehicle}/fuse/path"


def deadreckoning_path_topic(vehicle: str) -> str:
    return f"/{vehicle}/deadreckoning/path"


def ground_truth_path_topic(vehicle: str) -> str:
    return f"/{vehicle}/ground_truth/path"


@dataclass(frozen=True)
class ResultDecimation:
    """How much of a long run goes into result.mcap (module docstring): a growing topic
    (paths, map) every `period_ns`, stretched so that it has at most `max_messages`
    messages; at most `max_path_poses` poses per Path; at most `max_map_points` points in
    all the map clouds together (the map period stretched further when needed)."""

    period_ns: int = 1_000_000_000
    max_messages: int = 300
    max_path_poses: int = 1000
    max_map_points: int = 2_000_000


def map_cloud(table: LandmarkMap) -> np.ndarray:
    """(N,) structured array `CLOUD_DTYPE` for the PointCloud2 of the map: the fields of
    `map.ply` (x y z in the nav frame, std, id, n_obs)."""
    v = map_vertices(table)
    cloud = np.empty(len(table), dtype=CLOUD_DTYPE)
    for name in CLOUD_DTYPE.names or ():
        cloud[name] = v[name]
    return cloud


def snapshot_times(t0_ns: int, t1_ns: int, period_ns: int, max_count: int) -> I64:
    """t0, t0 + p, t0 + 2p, ... < t1 with p = period_ns, stretched so that there are at most
    `max_count` (>= 1) times. Empty when t1 <= t0."""
    span = int(t1_ns) - int(t0_ns)
    if span <= 0:
        return np.zeros(0, dtype=np.int64)
    p = max(int(period_ns), -(-span // max(int(max_count), 1)))
    return np.arange(int(t0_ns), int(t1_ns), p, dtype=np.int64)


def thinned(n: int, most: int) -> I64:
    """Indices 0..n-1, evenly thinned to at most `most` (>= 2), first and last kept."""
    if n <= most:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.round(np.linspace(0, n - 1, most)).astype(np.int64))


# a message to write: (stamp_ns, order among messages of one stamp, topic, type, payload):
# the payload (message fields, or CDR bytes) is made when written, so that the events of a
# long run stay small
_Event = tuple[int, int, str, str, Callable[[], dict[str, Any] | bytes]]


def _growing_paths(
    topic: str, table: PoseTable, times: I64, frame_id: str, most: int
) -> Iterator[_Event]:
    """The Path of `table`'s poses up to each of `times` (only when it grew), then all of it
    at its last stamp."""
    if not len(table):
        return
    last = int(table.stamps_ns[-1])
    shown = 0
    for t in [*(int(g) for g in times if g < last), last]:
        n = int(np.searchsorted(table.stamps_ns, t, side="right"))
        if n in (0, shown):
            continue
        shown = n
        idx = thinned(n, most)
        payload = partial(
            path_cdr,
            t,
            frame_id,
            table.stamps_ns[idx],
            table.p_nav_m[idx],
            table.q_nav_body_xyzw[idx],
        )
        yield t, 3, topic, "nav_msgs/msg/Path", payload


def _tf_fields(t: int, parent: str, child: str, p: F64, q: F64) -> dict[str, Any]:
    return tf_message_fields(t, [(parent, child, make_T(quat_xyzw_to_matrix(q), p))])


def _pose_events(
    vehicle: str, table: PoseTable, cov: F64 | None, frame_id: str
) -> Iterator[_Event]:
    """Per pose: /tf nav -> body and the pose with its covariance."""
    body = vehicle_names(vehicle).body_frame
    zeros = np.zeros((6, 6))
    for k, (t, p, q) in enumerate(
        zip(table.stamps_ns, table.p_nav_m, table.q_nav_body_xyzw, strict=True)
    ):
        t = int(t)
        yield t, 1, TF_TOPIC, "tf2_msgs/msg/TFMessage", partial(_tf_fields, t, frame_id, body, p, q)
        c = zeros if cov is None else cov[k]
        yield (
            t,
            2,
            pose_topic(vehicle),
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            partial(pose_with_covariance_fields, t, p, q, c, frame_id),
        )


def _cloud_fields(t: int, frame_id: str, cloud: np.ndarray, rows: I64 | None) -> dict[str, Any]:
    return point_cloud2_fields(t, frame_id, cloud if rows is None else cloud[rows])


def _map_events(
    landmarks: LandmarkMap, times: I64, final_ns: int, frame_id: str, most_points: int
) -> Iterator[_Event]:
    """The map as it grows: at each of `times` (thinned to the point budget) the landmarks
    first seen by then, when more than before; the whole map at `final_ns`."""
    cloud = map_cloud(landmarks)
    times = times[times < final_ns]
    if len(cloud):
        budget = most_points // len(cloud) - 1  # snapshots besides the final one
        times = times[thinned(len(times), budget)] if budget >= 2 else times[:0]
    order = np.argsort(landmarks.first_seen_ns, kind="stable")
    first_sorted = landmarks.first_seen_ns[order]
    shown = 0
    for t in (int(g) for g in times):
        k = int(np.searchsorted(first_sorted, t, side="right"))
        if k in (0, shown):
            continue
        shown = k
        rows = np.sort(order[:k])
        yield t, 4, MAP_TOPIC, _CLOUD, partial(_cloud_fields, t, frame_id, cloud, rows)
    yield (
        int(final_ns),
        4,
        MAP_TOPIC,
        _CLOUD,
        partial(_cloud_fields, int(final_ns), frame_id, cloud, None),
    )


def _static_transforms(rigs: Mapping[str, StereoRig]) -> list[tuple[str, str, F64]]:
    out: list[tuple[str, str, F64]] = [(ENU_FRAME_ID, NAV_FRAME_ID, T_ENU_NAV)]
    for vehicle, rig in rigs.items():
        names = vehicle_names(vehicle)
        out.append((names.body_frame, names.left_frame, np.asarray(rig.left.T_body_cam)))
        out.append((names.body_frame, names.right_frame, np.asarray(rig.right.T_body_cam)))
    return out


def _span(
    estimates: list[PoseTable], truths: list[PoseTable], landmarks: LandmarkMap
) -> tuple[int, int]:
    """(first stamp of any table, last stamp of the estimates): the time the snapshots
    span, and the map's final stamp. Without any pose, the map's last observation."""
    starts = [int(t.stamps_ns[0]) for t in (*estimates, *truths) if len(t)]
    ends = [int(t.stamps_ns[-1]) for t in estimates if len(t)]
    ends = ends or [int(t.stamps_ns[-1]) for t in truths if len(t)]
    if not starts:
        last = int(landmarks.last_seen_ns.max()) if len(landmarks) else 0
        return last, last
    return min(starts), max(ends)


def write_result_mcap(
    path: Path,
    trajectories: Mapping[str, PoseTable],
    landmarks: LandmarkMap,
    *,
    pose_covariances: Mapping[str, F64] | None = None,
    deadreckoning: Mapping[str, PoseTable] | None = None,
    ground_truth: Mapping[str, PoseTable] | None = None,
    rigs: Mapping[str, StereoRig] | None = None,
    frame_id: str = NAV_FRAME_ID,
    metadata: Mapping[str, str] | None = None,
    decimation: ResultDecimation = ResultDecimation(),
) -> None:
    """Write `result.mcap` (ROS 2, CDR; the module docstring lists the topics), poses in
    `frame_id` (the NED nav frame). `pose_covariances[v]` (N, 6, 6) over (x, y, z, roll,
    pitch, yaw) at `trajectories[v]`'s stamps (zeros where not given); `ground_truth[v]`
    in the nav frame; `rigs[v]` for the camera frames. Vehicles with no pose get no
    messages. Metadata record `cvslam.fuse`: frame_id, nav_frame NED, display_frame enu,
    vehicles, landmarks count, and `metadata`. Temporary name, renamed when complete."""
    covs = dict(pose_covariances or {})
    extra = {
        deadreckoning_path_topic: dict(deadreckoning or {}),
        ground_truth_path_topic: {v: t for v, t in (ground_truth or {}).items() if len(t)},
    }
    rigs = dict(rigs or {})
    for vehicle in {
        *trajectories,
        *extra[deadreckoning_path_topic],
        *extra[ground_truth_path_topic],
        *rigs,
    }:
        vehicle_names(vehicle)  # a CvslamError for a name that cannot be part of a topic
    for vehicle, cov in covs.items():
        n = len(trajectories[vehicle])
        if np.shape(cov) != (n, 6, 6):
            raise ValueError(
                f"pose covariances of {vehicle}: shape {np.shape(cov)}, expected ({n}, 6, 6)"
            )
    t0, t_end = _span(
        [*trajectories.values(), *extra[deadreckoning_path_topic].values()],
        list(extra[ground_truth_path_topic].values()),
        landmarks,
    )
    d = decimation
    times = snapshot_times(t0, t_end, d.period_ns, d.max_messages)

    static = partial(tf_message_fields, t0, _static_transforms(rigs))
    events: list[_Event] = [(t0, 0, TF_STATIC_TOPIC, "tf2_msgs/msg/TFMessage", static)]
    for vehicle, table in trajectories.items():
        events += _pose_events(vehicle, table, covs.get(vehicle), frame_id)
        events += _growing_paths(path_topic(vehicle), table, times, frame_id, d.max_path_poses)
    for topic_of, by_vehicle in extra.items():
        for vehicle, table in by_vehicle.items():
            events += _growing_paths(topic_of(vehicle), table, times, frame_id, d.max_path_poses)
    events += _map_events(landmarks, times, t_end, frame_id, d.max_map_points)
    events.sort(key=lambda e: (e[0], e[1]))

    info = {
        "frame_id": frame_id,
        "nav_frame": "NED",
        "display_frame": ENU_FRAME_ID,
        "vehicles": OBSERVER_SEPARATOR.join(trajectories),
        "landmarks": str(len(landmarks)),
        **{str(k): str(v) for k, v in (metadata or {}).items()},
    }
    with LogWriter(path) as w:
        for t, _, topic, datatype, make in events:
            payload = make()
            if isinstance(payload, bytes):
                w.write_raw(topic, datatype, payload, t)
            else:
                w.write(topic, datatype, payload, t)
        w.add_metadata(RESULT_METADATA_NAME, info)
