"""From log files to per-vehicle, time-ordered records.

`open_logs` opens each log with the reader its kind needs (`log_open.py`), the logs bound to
vehicles (`logs.vehicles.<name>.log`, `NAME=PATH` on the command line) included. `LogSet`
takes one or more `LogSource`s and the `logs` config section and composes:
- `topic_map.py`: which topics of which log belong to which vehicle, in which role (a log
  bound to a vehicle, explicit `logs.vehicles`, or discovered from the topic templates of
  `logs.vehicle_defaults`); one vehicle's topic coming from two logs over the same time is
  an error;
- `calibration.py`: each vehicle's stereo rig (CameraInfo, rig config, `/tf_static`),
  resolved once, before its images stream;
- `log_merge.py`: the logs merged by log time and put in header-stamp order by a bounded
  reorder window; `ros_messages.py`: messages -> typed records (`ImuSample`,
  `OdometryRecord`, `PoseRecord`, its world frame converted to NED by
  `geometry/nav_frames.py`; images decoded by `images.py`, their stamps moved by the rig's
  `camera_time_offset_ns`);
- `stamp_screen.py`: messages whose stamps cannot be used (before 1970, astray, duplicated,
  out of order beyond the window) dropped and counted;
- `stereo_pairing.py`: left and right images whose stamps differ by at most the tolerance
  paired into `StereoFrame`s;
- `log_stats.py`: per-topic statistics (counts, rates, gaps, stamps going backwards, samples
  dropped) and the list of problems for `cvslam info`.

Memory is bounded by the reorder window and the pairing tolerance, not by the log length.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from cvslam_cli.config import LogsConfig, VehicleConfig
from cvslam_cli.errors import CvslamError, LogError
from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.geometry.nav_frames import pose_to_nav
from cvslam_cli.io.calibration import Calibration, StaticTransforms
from cvslam_cli.io.images import ImageDecodeError, decode_compressed, decode_raw
from cvslam_cli.io.log_merge import ReorderWindow, merged_messages
from cvslam_cli.io.log_open import open_log
from cvslam_cli.io.log_stats import Problems, TopicStats, VehicleStats
from cvslam_cli.io.mcap_source import LogSource, RawMessage, TopicInfo
from cvslam_cli.io.ros_messages import CONVERTERS, stamp_ns_of
from cvslam_cli.io.run_layout import EXTRACT_STAGE
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.stamp_screen import StampScreen
from cvslam_cli.io.stereo_pairing import StereoPairer
from cvslam_cli.io.topic_map import map_topics
from cvslam_cli.records.log import ImageRecord, ImuSample, OdometryRecord, PoseRecord, Record
from cvslam_cli.records.poses import PoseTable

_IMAGE_ROLES = ("left_image", "right_image")
_UNBOUND = VehicleConfig()
_RECORD_ROLES = {ImuSample: "imu", OdometryRecord: "odom", PoseRecord: "ground_truth"}


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
        self.problems = Problems(strict=strict)
        self._topics = map_topics(self.sources, cfg, self.names)
        self.topic_infos: dict[str, TopicInfo] = self._topics.infos
        self._source_of: dict[tuple[str, str], tuple[int, set[int]]] = {}
        self.vehicles = self._topics.vehicles
        self.stats = {name: VehicleStats() for name in self.vehicles}
        self._calibration = Calibration(self.sources, self._topics, cfg, self.names)
        self.peak_buffered = 0  # most records held by the reorder window at once
        self._resized: set[str] = set()  # image topics whose size changed (reported once)
        self.problems.add_source_warnings(self.sources, log_warning=True)

    @property
    def names(self) -> str:
        return ", ".join(s.name for s in self.sources)

    def unassigned_topics(self) -> list[TopicInfo]:
        return self._topics.unassigned()

    @property
    def static_transforms(self) -> StaticTransforms:
        return self._calibration.static_transforms

    def rig(self, vehicle: str) -> StereoRig:
        """Stereo calibration of `vehicle` (CalibrationError when none can be had)."""
        return self._calibration.rig(vehicle)

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
        stereo = [n for n in selected if self.vehicles[n].has_stereo]
        rigs = self._calibration.resolve(stereo if roles & set(_IMAGE_ROLES) else [])
        window = ReorderWindow(int(self.cfg.reorder_window_ms * 1e6))
        image_roles = {
            (v.name, v.topic(r)): r for v in self.vehicles.values() for r in _IMAGE_ROLES
        }
        pairer = StereoPairer(int(self.cfg.stereo_pair_tolerance_ms * 1e6), self.stats, image_roles)
        self._source_of = {}
        wanted = self._topics.wanted(selected, roles)
        screen = StampScreen()
        for i, raw in merged_messages(self.sources, wanted):
            key = (self._topics.role_of[(i, raw.topic)][0], raw.topic)
            try:
                if not screen.arrived(key, stamp_ns_of(raw.msg), raw.log_time_ns, raw.msg):
                    continue
                rec = self._convert(i, raw, rigs)
            except AttributeError as exc:  # a schema of that name without the fields it has
                raise LogError(
                    f"{self.names}: {raw.topic}: its {raw.schema_name or 'schema'} messages lack "
                    f"the field {exc.name!r} (a schema other than the ROS 2 one)"
                ) from None
            if rec is None:
                continue
            window.push(rec)
            self.peak_buffered = max(self.peak_buffered, window.peak)
            for ready in window.released():
                if self._in_order(screen, ready):
                    yield from pairer.push(ready)
        for ready in window.drain():
            if self._in_order(screen, ready):
                yield from pairer.push(ready)
        pairer.finish()
        for text in screen.problems(self.names):
            self.problems.report("warning", text)
        self.problems.add_source_warnings(self.sources, log_warning=False)

    def _in_order(self, screen: StampScreen, rec: Record | ImageRecord) -> bool:
        """Whether a record the reorder window released is still in time order."""
        if isinstance(rec, ImageRecord):
            return screen.released((rec.vehicle, rec.topic), rec.stamp_ns)
        topic = self.vehicles[rec.vehicle].topic(_RECORD_ROLES[type(rec)])
        return screen.released((rec.vehicle, topic), rec.stamp_ns)

    def _convert(
        self, i: int, raw: RawMessage, rigs: dict[str, StereoRig | CvslamError]
    ) -> Record | ImageRecord | None:
        """The record of one message of log `i` (None: counted only, or dropped), its stamp
        observed."""
        vehicle, role = self._topics.role_of[(i, raw.topic)]
        self._check_one_log_at_a_time(i, vehicle, raw.topic)
        ts = self.stats[vehicle].topic(raw.topic, role, raw.schema_name)
        stamp_ns = stamp_ns_of(raw.msg)
        if not ts.observe(stamp_ns) and ts.backwards == 1:
            self.problems.report(
                "warning",
                f"{self.names}: {raw.topic}: timestamps go backwards "
                f"(first at stamp {stamp_ns} ns)",
            )
        if role in _IMAGE_ROLES:
            stamp_ns += self.vehicles[vehicle].config.rig.camera_time_offset_ns
            return self._image(raw, vehicle, role, stamp_ns, ts, rigs)
        convert = CONVERTERS.get(role)
        if convert is None:
            return None  # camera_info: counted, no record
        rec = convert(vehicle, stamp_ns, raw.msg)
        if rec is None:
            ts.dropped_nonfinite += 1
        elif isinstance(rec, PoseRecord):  # ground truth: its world frame -> nav, once
            p, q = pose_to_nav(
                rec.p_m, rec.q_xyzw, self.vehicles[vehicle].config.ground_truth_frame
            )
            rec = dataclasses.replace(rec, p_m=p, q_xyzw=q)
        return rec

    def _check_one_log_at_a_time(self, i: int, vehicle: str, topic: str) -> None:
        """A vehicle's topic may come from several logs one after the other (a recording in
        parts), never from two at once: messages merged by log time that come from a log
        again after another log's began mean the logs overlap in time, an error."""
        key = (vehicle, topic)
        last, done = self._source_of.get(key, (i, set()))
        if i != last:
            if i in done:
                self.problems.report(
                    "error",
                    f"{self.sources[i].name} and {self.sources[last].name}: both hold "
                    f"{topic} for vehicle {vehicle} over the same time; bind each log to its "
                    f"own vehicle (NAME=PATH, or logs.vehicles.NAME.log)",
                )
            done = done | {last}
        self._source_of[key] = (i, done)

    def _image(
        self,
        raw: RawMessage,
        vehicle: str,
        role: str,
        stamp_ns: int,
        ts: TopicStats,
        rigs: dict[str, StereoRig | CvslamError],
    ) -> ImageRecord | None:
        """The decoded image of a stereo vehicle; at the topic's first image, a calibration
        missing or made for another image size is an error."""
        try:
            if raw.schema_name == "sensor_msgs/msg/CompressedImage":
                img, enc = decode_compressed(raw.msg)
            else:
                img, enc = decode_raw(raw.msg)
        except ImageDecodeError as exc:
            self.problems.report("error", f"{self.names}: {raw.topic}: {exc}")
            return None
        first = ts.image_size is None
        size = (img.shape[1], img.shape[0])
        if not first and size != ts.image_size:
            assert ts.image_size is not None
            if raw.topic in self._resized:
                return None  # reported at its first image of another size
            self._resized.add(raw.topic)
            self.problems.report(
                "error",
                f"{self.names}: {raw.topic}: image size changes from "
                f"{ts.image_size[0]}x{ts.image_size[1]} to {size[0]}x{size[1]} at stamp "
                f"{stamp_ns} ns (one calibration cannot serve both)",
            )
            return None
        ts.image_size = size
        ts.encoding = enc
        if not self.vehicles[vehicle].has_stereo:
            return None  # a lone camera: counted, never paired
        if first:
            error = _calibration_error(rigs[vehicle], role, img, f"{self.names}: {raw.topic}")
            if error is not None:
                self.problems.report("error", str(error))
        return ImageRecord(stamp_ns, img, enc, str(raw.msg.header.frame_id), raw.topic, vehicle)


def all_log_paths(paths: Sequence[Path], cfg: LogsConfig) -> list[Path]:
    """`paths` and the logs bound to vehicles (`logs.vehicles.<name>.log`), each once."""
    out: list[Path] = []
    seen: set[Path] = set()
    for p in [*map(Path, paths), *(Path(v.log) for v in cfg.vehicles.values() if v.log)]:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            out.append(p)
    return out


def bind_logs(cfg: LogsConfig, bound: dict[str, Path]) -> LogsConfig:
    """`cfg` with each vehicle of `bound` bound to its log (`logs.vehicles.<name>.log`; a
    vehicle not configured starts from `logs.vehicle_defaults`)."""
    if not bound:
        return cfg
    vehicles = dict(cfg.vehicles)
    for name, path in bound.items():
        base = vehicles.get(name, cfg.vehicle_defaults)
        vehicles[name] = dataclasses.replace(base, log=str(Path(path).resolve()))
    return dataclasses.replace(cfg, vehicles=vehicles)


def with_run_bindings(cfg: LogsConfig, run_dir: Path) -> LogsConfig:
    """`cfg` with the vehicle-to-log bindings `extract` recorded for the run in `run_dir`
    (its `logs.vehicles.<name>.log`) for the vehicles `cfg` does not bind itself, so a later
    stage reads each vehicle from its own log without being told again."""
    recorded = RunDir(run_dir).load().get("stages", {}).get(EXTRACT_STAGE, {})
    vehicles = recorded.get("config", {}).get("logs", {}).get("vehicles", {})
    bound = {
        name: Path(v["log"])
        for name, v in vehicles.items()
        if isinstance(v, dict) and v.get("log") and not cfg.vehicles.get(name, _UNBOUND).log
    }
    return bind_logs(cfg, bound)


def require_logs(paths: Sequence[Path]) -> None:
    """LogError naming the first of `paths` that does not exist (before any work uses them)."""
    for p in paths:
        if not Path(p).exists():
            raise LogError(f"{p}: file not found")


def open_logs(paths: Sequence[Path], cfg: LogsConfig, *, strict: bool = True) -> LogSet:
    """The `LogSet` of the logs at `paths` and those bound to vehicles (`all_log_paths`), each
    opened by the reader its kind needs (`log_open.py`: MCAP, rosbag2 folder, sqlite3,
    ROS 1, compressed MCAP)."""
    return LogSet([open_log(p) for p in all_log_paths(paths, cfg)], cfg, strict=strict)


def _calibration_error(
    rig: StereoRig | CvslamError, role: str, image: np.ndarray, where: str
) -> CvslamError | None:
    """Why an image of `role` cannot be used with its vehicle's rig: no rig, or one whose
    camera was calibrated for another image size; None when it can."""
    if isinstance(rig, CvslamError):
        return rig
    cam = rig.left if role == "left_image" else rig.right
    try:
        cam.check_image_size(image.shape[1], image.shape[0], where)
    except CvslamError as exc:
        return exc
    return None


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
