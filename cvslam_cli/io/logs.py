"""From log files to per-vehicle, time-ordered records.

`LogSet` takes one or more `LogSource`s and the `logs` config section and:
- maps topics to vehicles (explicit `logs.vehicles`, or discovered from the topic templates
  of `logs.vehicle_defaults`, e.g. `/uav1/imu` -> vehicle `uav1`);
- finds each vehicle's stereo calibration (CameraInfo when present, else the rig config;
  extrinsics from `/tf_static` when it links the body frame to the camera frame, else the rig
  config, else the rectified right projection matrix);
- streams typed records (`StereoFrame`, `ImuSample`, `OdometryRecord`, `PoseRecord`) of all
  selected vehicles, merged across logs and ordered by header stamp through a bounded reorder
  window, pairing left and right images whose stamps differ by at most the tolerance;
- keeps per-topic statistics (counts, rates, gaps, stamps going backwards, samples dropped)
  and a list of problems for `cvslam info`.

Memory is bounded by the reorder window and the pairing tolerance, not by the log length.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import re
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from cvslam_cli.config import CameraConfig, LogsConfig, TopicMap, VehicleConfig
from cvslam_cli.errors import CalibrationError, CvslamError, LogError
from cvslam_cli.geometry.camera import CameraModel, StereoRig, translation_T
from cvslam_cli.geometry.rotations import invert_T, make_T, quat_xyzw_to_matrix
from cvslam_cli.io.images import ImageDecodeError, decode_compressed, decode_raw
from cvslam_cli.io.mcap_source import LogSource, RawMessage, TopicInfo
from cvslam_cli.records.log import (
    ImageRecord,
    ImuSample,
    OdometryRecord,
    PoseRecord,
    Record,
    StereoFrame,
)
from cvslam_cli.records.poses import PoseTable

log = logging.getLogger("cvslam")

Role = Literal[
    "left_image", "right_image", "left_info", "right_info", "imu", "odom", "ground_truth"
]
ROLES: tuple[Role, ...] = (
    "left_image",
    "right_image",
    "left_info",
    "right_info",
    "imu",
    "odom",
    "ground_truth",
)
EXPECTED_TYPES: dict[str, tuple[str, ...]] = {
    "left_image": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    "right_image": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    "left_info": ("sensor_msgs/msg/CameraInfo",),
    "right_info": ("sensor_msgs/msg/CameraInfo",),
    "imu": ("sensor_msgs/msg/Imu",),
    "odom": ("nav_msgs/msg/Odometry",),
    "ground_truth": ("geometry_msgs/msg/PoseStamped",),
}
_INTERVAL_SAMPLE = 1000  # intervals kept to estimate a topic's nominal period (median)


def stamp_ns_of(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


@dataclass(frozen=True)
class Problem:
    severity: Literal["error", "warning"]
    text: str


@dataclass
class TopicStats:
    """What was seen on one topic (filled while streaming)."""

    topic: str
    role: str
    schema_name: str
    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    backwards: int = 0
    dropped_nonfinite: int = 0
    image_size: tuple[int, int] | None = None  # (width, height)
    encoding: str | None = None
    _intervals: list[int] = field(default_factory=list)
    _late_intervals: list[int] = field(default_factory=list)

    def observe(self, stamp_ns: int) -> bool:
        """Record a stamp; False if it goes backwards (the message is still counted)."""
        self.count += 1
        ok = True
        if self.last_ns is not None:
            dt = stamp_ns - self.last_ns
            if dt < 0:
                self.backwards += 1
                ok = False
            elif len(self._intervals) < _INTERVAL_SAMPLE:
                self._intervals.append(dt)
            elif dt > 2 * self.nominal_period_ns:  # only candidate gaps need keeping
                self._late_intervals.append(dt)
        if self.first_ns is None:
            self.first_ns = stamp_ns
        if ok:
            self.last_ns = stamp_ns
        return ok

    @property
    def nominal_period_ns(self) -> float:
        return float(np.median(self._intervals)) if self._intervals else 0.0

    @property
    def rate_hz(self) -> float:
        p = self.nominal_period_ns
        return 1e9 / p if p > 0 else 0.0

    @property
    def span_s(self) -> float:
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        return (self.last_ns - self.first_ns) * 1e-9

    def gaps(self, factor: float) -> list[float]:
        """Intervals (s) longer than `factor` nominal periods."""
        p = self.nominal_period_ns
        if p <= 0:
            return []
        return [dt * 1e-9 for dt in self._intervals + self._late_intervals if dt > factor * p]


@dataclass
class VehicleStats:
    stereo_pairs: int = 0
    unpaired_left: int = 0
    unpaired_right: int = 0
    max_pair_offset_ns: int = 0
    topics: dict[str, TopicStats] = field(default_factory=dict)


@dataclass(frozen=True)
class VehicleTopics:
    """The topics of one vehicle in this set of logs; `present` lists roles found."""

    name: str
    config: VehicleConfig
    topics: TopicMap
    present: tuple[str, ...]

    def topic(self, role: str) -> str:
        return str(getattr(self.topics, role))

    @property
    def has_stereo(self) -> bool:
        return "left_image" in self.present and "right_image" in self.present


def _template_regex(template: str) -> re.Pattern[str] | None:
    if "{vehicle}" not in template:
        return None
    parts = [re.escape(p) for p in template.split("{vehicle}")]
    return re.compile("^" + "(?P<vehicle>[A-Za-z0-9_]+)".join(parts) + "$")


def _camera_from_config(cfg: CameraConfig, frame_id: str) -> CameraModel:
    K = np.array([[cfg.fx, 0.0, cfg.cx], [0.0, cfg.fy, cfg.cy], [0.0, 0.0, 1.0]])
    return CameraModel(
        width=cfg.width,
        height=cfg.height,
        K=K,
        D=np.asarray(cfg.distortion),
        distortion_model=cfg.distortion_model,
        T_body_cam=np.asarray(cfg.T_body_cam, dtype=float).reshape(4, 4),
        frame_id=frame_id,
        source="config",
    )


def camera_from_info(msg: Any, source: str) -> CameraModel:
    """CameraModel from a decoded sensor_msgs/msg/CameraInfo."""
    P = np.asarray(msg.p, dtype=float).reshape(3, 4)
    return CameraModel(
        width=int(msg.width),
        height=int(msg.height),
        K=np.asarray(msg.k, dtype=float).reshape(3, 3),
        D=np.asarray(msg.d, dtype=float),
        distortion_model=str(msg.distortion_model) or "none",
        R_rect=np.asarray(msg.r, dtype=float).reshape(3, 3),
        P=P if np.any(P) else None,
        frame_id=str(msg.header.frame_id),
        source=source,
    )


class StaticTransforms:
    """The tree of /tf_static transforms; `lookup(a, b)` gives T_a_b when a path exists."""

    def __init__(self) -> None:
        self._edges: dict[str, dict[str, np.ndarray]] = {}

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        self._edges.setdefault(parent, {})[child] = T_parent_child
        self._edges.setdefault(child, {})[parent] = invert_T(T_parent_child)

    def add_message(self, msg: Any) -> None:
        for tr in msg.transforms:
            t, q = tr.transform.translation, tr.transform.rotation
            T = make_T(
                quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])), np.array([t.x, t.y, t.z])
            )
            self.add(_strip(tr.header.frame_id), _strip(tr.child_frame_id), T)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.eye(4)
        seen = {target}
        queue: deque[tuple[str, np.ndarray]] = deque([(target, np.eye(4))])
        while queue:
            frame, T_target_frame = queue.popleft()
            for nxt, T_frame_nxt in self._edges.get(frame, {}).items():
                if nxt in seen:
                    continue
                T = T_target_frame @ T_frame_nxt
                if nxt == source:
                    return T
                seen.add(nxt)
                queue.append((nxt, T))
        return None


def _strip(frame: str) -> str:
    return frame.lstrip("/")


class LogSet:
    """Several logs read as one, split into vehicles (see the module docstring)."""

    def __init__(
        self, sources: Sequence[LogSource], cfg: LogsConfig, *, strict: bool = True
    ) -> None:
        if not sources:
            raise LogError("no log given")
        self.sources = list(sources)
        self.cfg = cfg
        self.strict = strict
        self.problems: list[Problem] = []
        self.topic_infos: dict[str, TopicInfo] = {}
        self._topic_source: dict[str, list[int]] = {}
        for i, src in enumerate(self.sources):
            for name, info in src.topics().items():
                old = self.topic_infos.get(name)
                if old is not None and old.schema_name != info.schema_name:
                    raise LogError(
                        f"{src.name}: {name}: type {info.schema_name} differs from "
                        f"{old.schema_name} in another log"
                    )
                count = info.message_count + (old.message_count if old else 0)
                self.topic_infos[name] = TopicInfo(name, info.schema_name, count)
                self._topic_source.setdefault(name, []).append(i)
        self.vehicles = self._map_vehicles()
        self._role_of: dict[str, tuple[str, str]] = {}
        for v in self.vehicles.values():
            for role in v.present:
                self._role_of[v.topic(role)] = (v.name, role)
        self.stats = {name: VehicleStats() for name in self.vehicles}
        self._tf: StaticTransforms | None = None
        self._rigs: dict[str, StereoRig] = {}
        self.peak_buffered = 0  # most records held by the reorder window at once
        for src in self.sources:
            for w in src.warnings:
                self._problem("warning", w)

    @property
    def names(self) -> str:
        return ", ".join(s.name for s in self.sources)

    # -- problems ------------------------------------------------------------------------

    def _problem(self, severity: Literal["error", "warning"], text: str) -> None:
        if severity == "error" and self.strict:
            raise LogError(text)
        p = Problem(severity, text)
        if p not in self.problems:
            self.problems.append(p)
            if severity == "warning":
                log.warning(text)

    def _collect_source_warnings(self) -> None:
        for src in self.sources:
            for w in src.warnings:
                p = Problem("warning", w)
                if p not in self.problems:
                    self.problems.append(p)

    # -- vehicles ------------------------------------------------------------------------

    def _resolve_topics(self, name: str, vcfg: VehicleConfig) -> tuple[TopicMap, list[str]]:
        topics = vcfg.topics.resolve(name)
        present: list[str] = []
        updates: dict[str, str] = {}
        for role in ROLES:
            topic = getattr(topics, role)
            compressed = f"{topic}/compressed"
            if (
                topic not in self.topic_infos
                and role.endswith("_image")
                and compressed in self.topic_infos
            ):
                topic = updates[role] = compressed
            if topic in self.topic_infos:
                present.append(role)
        if updates:
            topics = TopicMap(**{**topics.__dict__, **updates})
        return topics, present

    def _map_vehicles(self) -> dict[str, VehicleTopics]:
        cfg = self.cfg
        if cfg.vehicles:
            chosen = dict(cfg.vehicles)
        else:
            chosen = {}
            patterns = [
                p
                for p in (_template_regex(t) for t in cfg.vehicle_defaults.topics.__dict__.values())
                if p
            ]
            for topic in sorted(self.topic_infos):
                for pat in patterns:
                    m = pat.match(topic)
                    if m:
                        chosen.setdefault(m.group("vehicle"), cfg.vehicle_defaults)
        out: dict[str, VehicleTopics] = {}
        owner: dict[str, str] = {}
        for name, vcfg in sorted(chosen.items()):
            topics, present = self._resolve_topics(name, vcfg)
            if cfg.vehicles:
                self._check_named_topics(name, vcfg, topics, present)
            for role in present:
                t = getattr(topics, role)
                if t in owner:
                    raise LogError(
                        f"{self.names}: topic {t} is mapped to both vehicle "
                        f"{owner[t]} and vehicle {name}"
                    )
                owner[t] = name
                info = self.topic_infos[t]
                if info.schema_name not in EXPECTED_TYPES[role]:
                    raise LogError(
                        f"{self.names}: {t}: has type {info.schema_name}, expected "
                        f"{' or '.join(EXPECTED_TYPES[role])} for {name}'s {role}"
                    )
            out[name] = VehicleTopics(name, vcfg, topics, tuple(present))
        return out

    def _check_named_topics(
        self, name: str, vcfg: VehicleConfig, topics: TopicMap, present: list[str]
    ) -> None:
        """A topic the config names (differs from the default template) must exist."""
        default = self.cfg.vehicle_defaults.topics.resolve(name)
        for role in ROLES:
            named = getattr(vcfg.topics.resolve(name), role)
            if role not in present and named != getattr(default, role):
                raise LogError(
                    f"{self.names}: topic {named} (logs.vehicles.{name}.topics."
                    f"{role}) is not in the log"
                )
        if not present:
            raise LogError(
                f"{self.names}: none of vehicle {name}'s topics are in the log "
                f"(expected e.g. {topics.left_image} or {topics.imu})"
            )

    def unassigned_topics(self) -> list[TopicInfo]:
        return [i for t, i in sorted(self.topic_infos.items()) if t not in self._role_of]

    # -- calibration ---------------------------------------------------------------------

    def _first(self, topic: str) -> RawMessage | None:
        for i in self._topic_source.get(topic, []):
            for raw in self.sources[i].messages([topic]):
                return raw
        return None

    @property
    def static_transforms(self) -> StaticTransforms:
        if self._tf is None:
            self._tf = StaticTransforms()
            topic = self.cfg.tf_static_topic
            for i in self._topic_source.get(topic, []):
                for raw in self.sources[i].messages([topic]):
                    if raw.schema_name == "tf2_msgs/msg/TFMessage":
                        self._tf.add_message(raw.msg)
        return self._tf

    def rig(self, vehicle: str) -> StereoRig:
        """Stereo calibration of `vehicle` (CalibrationError when none can be had)."""
        if vehicle in self._rigs:
            return self._rigs[vehicle]
        v = self.vehicles[vehicle]
        rig_cfg = v.config.rig
        body_frame = rig_cfg.body_frame.replace("{vehicle}", vehicle)
        cams: list[CameraModel] = []
        for side, cam_cfg in (("left", rig_cfg.left), ("right", rig_cfg.right)):
            info_topic = v.topic(f"{side}_info")
            raw = self._first(info_topic) if f"{side}_info" in v.present else None
            if raw is not None:
                cam = camera_from_info(raw.msg, f"CameraInfo {info_topic}")
                extr = cam_cfg.T_body_cam
            elif cam_cfg.configured:
                img = self._first(v.topic(f"{side}_image"))
                cam = _camera_from_config(cam_cfg, img.msg.header.frame_id if img else "")
                cam = _replace(cam, source=f"config logs.vehicles.{vehicle}.rig.{side}")
                extr = cam_cfg.T_body_cam
            else:
                raise CalibrationError(
                    f"{self.names}: vehicle {vehicle}: no calibration for the {side} camera "
                    f"(no CameraInfo on {info_topic} and rig.{side} is not configured)"
                )
            T_body_cam = (
                self.static_transforms.lookup(body_frame, cam.frame_id) if cam.frame_id else None
            )
            if T_body_cam is None:
                T_body_cam = np.asarray(extr, dtype=float).reshape(4, 4)
            else:
                cam = _replace(cam, source=cam.source + f" + {self.cfg.tf_static_topic}")
            cams.append(_replace(cam, T_body_cam=T_body_cam))
        left, right = cams
        rig = StereoRig(left, right)
        b_p = rig.baseline_from_projection_m
        if rig.baseline_m < 1e-6 and b_p is not None and b_p > 0:
            # rectified pair with no extrinsics: the right camera sits b along the left's x
            right = _replace(right, T_body_cam=left.T_body_cam @ translation_T(b_p))
            rig = StereoRig(left, right)
        rig.validate(f"{self.names}: vehicle {vehicle}")
        self._rigs[vehicle] = rig
        return rig

    # -- records -------------------------------------------------------------------------

    def _raw_stream(self, topics: set[str]) -> Iterator[RawMessage]:
        streams = []
        for i, src in enumerate(self.sources):
            mine = [t for t in topics if i in self._topic_source.get(t, [])]
            if mine:
                streams.append(src.messages(mine))
        if len(streams) == 1:
            yield from streams[0]
        else:
            yield from heapq.merge(*streams, key=lambda r: r.log_time_ns)

    def records(
        self,
        vehicles: Iterable[str] | None = None,
        roles: Iterable[str] = ("left_image", "right_image", "imu", "odom", "ground_truth"),
    ) -> Iterator[Record]:
        """Typed records of `vehicles` (all by default), ordered by header stamp."""
        selected = list(self.vehicles) if vehicles is None else list(vehicles)
        for name in selected:
            if name not in self.vehicles:
                raise LogError(
                    f"{self.names}: no vehicle {name!r} in the logs (found: "
                    f"{', '.join(self.vehicles) or 'none'})"
                )
        roles = set(roles)
        topics = {
            self.vehicles[n].topic(r)
            for n in selected
            for r in self.vehicles[n].present
            if r in roles
        }
        window_ns = int(self.cfg.reorder_window_ms * 1e6)
        heap: list[tuple[int, int, Any]] = []
        counter = itertools.count()
        newest = -(2**63)
        pairer = _StereoPairer(
            int(self.cfg.stereo_pair_tolerance_ms * 1e6), self.stats, self._role_of
        )
        for raw in self._raw_stream(topics):
            rec = self._convert(raw)
            if rec is None:
                continue
            heapq.heappush(heap, (rec.stamp_ns, next(counter), rec))
            self.peak_buffered = max(self.peak_buffered, len(heap))
            newest = max(newest, rec.stamp_ns)
            while heap and heap[0][0] <= newest - window_ns:
                yield from pairer.push(heapq.heappop(heap)[2])
        while heap:
            yield from pairer.push(heapq.heappop(heap)[2])
        pairer.finish()
        self._collect_source_warnings()

    def _topic_stats(self, vehicle: str, role: str, raw: RawMessage) -> TopicStats:
        vs = self.stats[vehicle]
        ts = vs.topics.get(raw.topic)
        if ts is None:
            ts = vs.topics[raw.topic] = TopicStats(raw.topic, role, raw.schema_name)
        return ts

    def _convert(self, raw: RawMessage) -> Any:
        vehicle, role = self._role_of[raw.topic]
        ts = self._topic_stats(vehicle, role, raw)
        stamp = stamp_ns_of(raw.msg)
        if not ts.observe(stamp) and ts.backwards == 1:
            self._problem(
                "warning",
                f"{self.names}: {raw.topic}: timestamps go backwards (first at stamp {stamp} ns)",
            )
        msg = raw.msg
        if role in ("left_image", "right_image"):
            return self._image(raw, vehicle, role, stamp, ts)
        if role == "imu":
            w, a = msg.angular_velocity, msg.linear_acceleration
            gyro = np.array([w.x, w.y, w.z], dtype=float)
            acc = np.array([a.x, a.y, a.z], dtype=float)
            if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(acc))):
                ts.dropped_nonfinite += 1
                return None
            return ImuSample(vehicle, stamp, gyro, acc, str(msg.header.frame_id))
        if role == "odom":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
            vals = np.array(
                [p.x, p.y, p.z, q.x, q.y, q.z, q.w, lin.x, lin.y, lin.z, ang.x, ang.y, ang.z],
                dtype=float,
            )
            if not np.all(np.isfinite(vals)):
                ts.dropped_nonfinite += 1
                return None
            return OdometryRecord(
                vehicle,
                stamp,
                str(msg.header.frame_id),
                str(msg.child_frame_id),
                vals[0:3],
                vals[3:7],
                vals[7:10],
                vals[10:13],
                np.asarray(msg.pose.covariance).reshape(6, 6),
                np.asarray(msg.twist.covariance).reshape(6, 6),
            )
        if role == "ground_truth":
            p, q = msg.pose.position, msg.pose.orientation
            vals = np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], dtype=float)
            if not np.all(np.isfinite(vals)):
                ts.dropped_nonfinite += 1
                return None
            return PoseRecord(vehicle, stamp, str(msg.header.frame_id), vals[:3], vals[3:])
        return None

    def _image(
        self, raw: RawMessage, vehicle: str, role: str, stamp: int, ts: TopicStats
    ) -> ImageRecord | None:
        try:
            if raw.schema_name == "sensor_msgs/msg/CompressedImage":
                img, enc = decode_compressed(raw.msg)
            else:
                img, enc = decode_raw(raw.msg)
        except ImageDecodeError as exc:
            self._problem("error", f"{self.names}: {raw.topic}: {exc}")
            return None
        first = ts.image_size is None
        ts.image_size = (img.shape[1], img.shape[0])
        ts.encoding = enc
        if not self.vehicles[vehicle].has_stereo:
            return None  # a lone camera: counted, never paired
        if first:
            try:
                cam = self.rig(vehicle).left if role == "left_image" else self.rig(vehicle).right
                cam.check_image_size(img.shape[1], img.shape[0], f"{self.names}: {raw.topic}")
            except CvslamError as exc:
                self._problem("error", str(exc))
        return ImageRecord(stamp, img, enc, str(raw.msg.header.frame_id), raw.topic)


def _replace(cam: CameraModel, **changes: Any) -> CameraModel:
    from dataclasses import replace

    return replace(cam, **changes)


class _StereoPairer:
    """Pairs left/right images of each vehicle arriving in stamp order.

    Images arrive in stamp order, so when one with stamp t arrives, queued images (either
    side) older than t - tolerance can never be paired and are counted as unpaired; the
    oldest queued image of the other side within the tolerance is its partner.
    """

    def __init__(
        self, tolerance_ns: int, stats: dict[str, VehicleStats], role_of: dict[str, tuple[str, str]]
    ) -> None:
        self.tol = tolerance_ns
        self.stats = stats
        self.role_of = role_of
        self.queues: dict[tuple[str, str], deque[ImageRecord]] = {}

    def _unpaired(self, vehicle: str, side: str, n: int = 1) -> None:
        vs = self.stats[vehicle]
        setattr(vs, f"unpaired_{side}", getattr(vs, f"unpaired_{side}") + n)

    def push(self, rec: Any) -> Iterator[Record]:
        if not isinstance(rec, ImageRecord):
            yield rec
            return
        vehicle, role = self.role_of[rec.topic]
        side = role.removesuffix("_image")
        other_side = "right" if side == "left" else "left"
        for s in (side, other_side):
            q = self.queues.setdefault((vehicle, s), deque())
            while q and q[0].stamp_ns < rec.stamp_ns - self.tol:
                q.popleft()
                self._unpaired(vehicle, s)
        other = self.queues[(vehicle, other_side)]
        if not other:
            self.queues[(vehicle, side)].append(rec)
            return
        mate = other.popleft()
        left, right = (rec, mate) if side == "left" else (mate, rec)
        vs = self.stats[vehicle]
        vs.stereo_pairs += 1
        vs.max_pair_offset_ns = max(vs.max_pair_offset_ns, abs(right.stamp_ns - left.stamp_ns))
        yield StereoFrame(vehicle, left.stamp_ns, left, right)

    def finish(self) -> None:
        for (vehicle, side), q in self.queues.items():
            self._unpaired(vehicle, side, len(q))
            q.clear()


def ground_truth_tables(logs: LogSet, vehicles: Sequence[str]) -> dict[str, PoseTable]:
    """Each vehicle's ground-truth poses from the logs' ground-truth topic; LogError naming
    the topic for a vehicle with fewer than two."""
    recs: dict[str, list[PoseRecord]] = {v: [] for v in vehicles}
    for rec in logs.records(vehicles=list(vehicles), roles=("ground_truth",)):
        if isinstance(rec, PoseRecord):
            recs[rec.vehicle].append(rec)
    out = {}
    for v, g in recs.items():
        if len(g) < 2:
            raise LogError(
                f"{logs.names}: vehicle {v}: no ground-truth poses on "
                f"{logs.vehicles[v].topic('ground_truth')}"
            )
        out[v] = PoseTable(
            np.array([r.stamp_ns for r in g], dtype=np.int64),
            np.array([r.p_m for r in g], dtype=float),
            np.array([r.q_xyzw for r in g], dtype=float),
        )
    return out
