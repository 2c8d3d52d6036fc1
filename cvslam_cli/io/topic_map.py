"""Which topics of a set of logs belong to which vehicle, and in which role.

A vehicle bound to a log file (`logs.vehicles.<name>.log`, or `NAME=PATH` on the command line)
is read from that log only, its topic names used as they are in it: two robots recorded with
the same topic names stay two vehicles. Its topics are those of its topic map; when none of
them is in the log, the one vehicle the default templates find there (under whatever name it
was recorded) is it.

The vehicles of the other logs are those of `logs.vehicles` (without `log`) when the config
names any; otherwise they are discovered from the topic templates of `logs.vehicle_defaults`
(`/{vehicle}/imu` matches `/uav1/imu`: vehicle `uav1`). Each vehicle's topics come from its
templates, an image topic falling back to its `/compressed` variant; a topic the config names
must be in the logs, a topic of a log may belong to one vehicle only (the error names both
mappings), and each must have the message type of its role (DESIGN.md section 4).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from cvslam_cli.config import LogsConfig, TopicMap, VehicleConfig
from cvslam_cli.errors import LogError
from cvslam_cli.io.mcap_source import LogSource, TopicInfo
from cvslam_cli.io.ros_messages import GROUND_TRUTH_TYPES

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
    "ground_truth": GROUND_TRUTH_TYPES,
}


@dataclass(frozen=True)
class VehicleTopics:
    """The topics of one vehicle in this set of logs; `present` lists roles found.

    sources: indices (into the list of logs) of the logs its topics are read from (one for a
    vehicle bound to a log file, `logs.vehicles.<name>.log`); infos: each present role's
    topic, its message count summed over those logs; template_name: the name `{vehicle}` is
    replaced by in its topic and frame templates (a bound log's own vehicle name when its
    topics follow the default templates under another name)."""

    name: str
    config: VehicleConfig
    topics: TopicMap
    present: tuple[str, ...]
    sources: tuple[int, ...] = ()
    infos: dict[str, TopicInfo] = field(default_factory=dict)
    template_name: str = ""

    def topic(self, role: str) -> str:
        return str(getattr(self.topics, role))

    @property
    def has_stereo(self) -> bool:
        return "left_image" in self.present and "right_image" in self.present


@dataclass(frozen=True)
class LogTopics:
    """The topics of a set of logs and who they belong to.

    infos: every topic of the logs, its message count summed over them.
    logs_of: indices (into the list of sources) of the logs holding each topic.
    vehicles: the vehicles found, by name (sorted).
    role_of: (vehicle, role) of each (log index, topic) mapped to a vehicle.
    """

    infos: dict[str, TopicInfo]
    logs_of: dict[str, list[int]]
    vehicles: dict[str, VehicleTopics]
    role_of: dict[tuple[int, str], tuple[str, str]]

    def unassigned(self) -> list[TopicInfo]:
        """The topics no vehicle uses (in any log), sorted by name."""
        used = {t for _, t in self.role_of}
        return [i for t, i in sorted(self.infos.items()) if t not in used]

    def wanted(self, vehicles: Sequence[str], roles: Collection[str]) -> dict[int, list[str]]:
        """The topics to read from each log for `roles` of `vehicles`."""
        out: dict[int, list[str]] = {}
        for (i, topic), (v, role) in self.role_of.items():
            if v in vehicles and role in roles:
                out.setdefault(i, []).append(topic)
        return out


def map_topics(sources: Sequence[LogSource], cfg: LogsConfig, names: str) -> LogTopics:
    """The `LogTopics` of `sources` (`names`: the logs' names, for messages); LogError for a
    topic whose type differs between logs and for every mapping problem (module docstring)."""
    bound = _bound_sources(sources, cfg)
    infos, logs_of = _merge_topics(sources, same_types=not bound)
    vehicles: dict[str, VehicleTopics] = {}
    for name, i in sorted(bound.items()):
        vehicles[name] = _bound_vehicle(name, cfg.vehicles[name], i, sources[i], cfg)
    free = [i for i in range(len(sources)) if i not in bound.values()]
    if free:
        free_infos, free_logs_of = _merge_topics([sources[i] for i in free])
        free_logs_of = {t: [free[j] for j in js] for t, js in free_logs_of.items()}
        named = {n: v for n, v in cfg.vehicles.items() if not v.log}
        for name, v in _map_vehicles(free_infos, cfg, named, names).items():
            if name in vehicles:
                raise LogError(
                    f"{names}: vehicle {name} is bound to {cfg.vehicles[name].log} and also "
                    "found in the other logs; give each vehicle one name"
                )
            srcs = sorted({i for role in v.present for i in free_logs_of[v.topic(role)]})
            vehicles[name] = dataclasses.replace(v, sources=tuple(srcs))
    role_of = _owners(sources, vehicles, names)
    return LogTopics(infos, logs_of, dict(sorted(vehicles.items())), role_of)


def _bound_sources(sources: Sequence[LogSource], cfg: LogsConfig) -> dict[str, int]:
    """vehicle -> index of the log it is bound to (`logs.vehicles.<name>.log`)."""
    by_path = {Path(s.name).resolve(): i for i, s in enumerate(sources)}
    out: dict[str, int] = {}
    for name, v in cfg.vehicles.items():
        if not v.log:
            continue
        i = by_path.get(Path(v.log).resolve())
        if i is None:
            raise LogError(f"logs.vehicles.{name}.log: {v.log} is not among the logs read")
        other = next((n for n, j in out.items() if j == i), None)
        if other is not None:
            raise LogError(
                f"{v.log}: bound to both vehicle {other} and vehicle {name} "
                f"(logs.vehicles.{other}.log, logs.vehicles.{name}.log)"
            )
        out[name] = i
    return out


def _bound_vehicle(
    name: str, vcfg: VehicleConfig, i: int, src: LogSource, cfg: LogsConfig
) -> VehicleTopics:
    """The vehicle of a log bound to it: its topic map as configured, else the one vehicle
    the default templates find in that log (under whatever name it was recorded)."""
    infos = src.topics()
    template_name = name
    topics, present = _resolve_topics(infos, name, vcfg)
    if not present:
        found = sorted(_discover_vehicles(infos, cfg))
        if len(found) > 1:
            raise LogError(
                f"{src.name}: holds vehicles {', '.join(found)}, so it cannot be vehicle {name} "
                f"alone; give it without '{name}=' or set logs.vehicles.{name}.topics"
            )
        if found:
            template_name = found[0]
            topics, present = _resolve_topics(infos, template_name, vcfg)
    if not present:
        raise LogError(
            f"{src.name}: none of vehicle {name}'s topics are in it (expected e.g. "
            f"{topics.left_image} or {topics.imu}; topics seen: {', '.join(sorted(infos))}); "
            f"set logs.vehicles.{name}.topics"
        )
    _check_types(infos, name, topics, present, src.name)
    role_infos = {r: infos[getattr(topics, r)] for r in present}
    return VehicleTopics(name, vcfg, topics, tuple(present), (i,), role_infos, template_name)


def _owners(
    sources: Sequence[LogSource], vehicles: dict[str, VehicleTopics], names: str
) -> dict[tuple[int, str], tuple[str, str]]:
    """(log index, topic) -> (vehicle, role); LogError naming both mappings of a topic
    mapped twice in one log."""
    role_of: dict[tuple[int, str], tuple[str, str]] = {}
    for v in vehicles.values():
        for role in v.present:
            t = v.topic(role)
            for i in v.sources:
                if t not in sources[i].topics():
                    continue
                old = role_of.get((i, t))
                if old is not None:
                    raise LogError(
                        f"{sources[i].name}: topic {t} is mapped twice: as "
                        f"{_mapping(vehicles[old[0]], old[1])} and as {_mapping(v, role)}"
                    )
                role_of[(i, t)] = (v.name, role)
    return role_of


def _mapping(v: VehicleTopics, role: str) -> str:
    """Where a vehicle's topic for `role` comes from, for messages."""
    named = getattr(v.config.topics, role)
    default = getattr(TopicMap(), role)
    key = (
        f"logs.vehicles.{v.name}.topics.{role}"
        if named != default
        else f"the template {default} of logs.vehicle_defaults.topics.{role}"
    )
    return f"vehicle {v.name}'s {role} ({key})"


def _merge_topics(
    sources: Sequence[LogSource], *, same_types: bool = True
) -> tuple[dict[str, TopicInfo], dict[str, list[int]]]:
    """Every topic of `sources` (message counts summed) and the logs holding it; with
    `same_types`, LogError for a topic whose type differs between logs (logs bound to
    different vehicles may differ: their topics are never merged)."""
    infos: dict[str, TopicInfo] = {}
    logs_of: dict[str, list[int]] = {}
    for i, src in enumerate(sources):
        for name, info in src.topics().items():
            old = infos.get(name)
            if same_types and old is not None and old.schema_name != info.schema_name:
                raise LogError(
                    f"{src.name}: {name}: type {info.schema_name} differs from "
                    f"{old.schema_name} in another log"
                )
            count = info.message_count + (old.message_count if old else 0)
            infos[name] = TopicInfo(name, info.schema_name, count)
            logs_of.setdefault(name, []).append(i)
    return infos, logs_of


def _template_regex(template: str) -> re.Pattern[str] | None:
    if "{vehicle}" not in template:
        return None
    parts = [re.escape(p) for p in template.split("{vehicle}")]
    return re.compile("^" + "(?P<vehicle>[A-Za-z0-9_]+)".join(parts) + "$")


def _discover_vehicles(infos: dict[str, TopicInfo], cfg: LogsConfig) -> dict[str, VehicleConfig]:
    """Vehicle names matched by the default topic templates, each with the default config."""
    patterns = [
        p for p in (_template_regex(t) for t in cfg.vehicle_defaults.topics.__dict__.values()) if p
    ]
    chosen: dict[str, VehicleConfig] = {}
    for topic in sorted(infos):
        for pat in patterns:
            m = pat.match(topic)
            if m:
                chosen.setdefault(m.group("vehicle"), cfg.vehicle_defaults)
    return chosen


def _resolve_topics(
    infos: dict[str, TopicInfo], name: str, vcfg: VehicleConfig
) -> tuple[TopicMap, list[str]]:
    """A vehicle's topic names (an absent image topic replaced by its `/compressed` variant
    when that is present) and the roles present in the logs."""
    topics = vcfg.topics.resolve(name)
    present: list[str] = []
    updates: dict[str, str] = {}
    for role in ROLES:
        topic = getattr(topics, role)
        compressed = f"{topic}/compressed"
        if topic not in infos and role.endswith("_image") and compressed in infos:
            topic = updates[role] = compressed
        if topic in infos:
            present.append(role)
    if updates:
        topics = TopicMap(**{**topics.__dict__, **updates})
    return topics, present


def _map_vehicles(
    infos: dict[str, TopicInfo],
    cfg: LogsConfig,
    named: dict[str, VehicleConfig],
    names: str,
) -> dict[str, VehicleTopics]:
    """The vehicles of logs no vehicle is bound to: those `named` in the config, else those
    the default templates discover."""
    chosen = dict(named) if named else _discover_vehicles(infos, cfg)
    out: dict[str, VehicleTopics] = {}
    for name, vcfg in sorted(chosen.items()):
        topics, present = _resolve_topics(infos, name, vcfg)
        if named:
            _check_named_topics(cfg, names, name, vcfg, topics, present)
        _check_types(infos, name, topics, present, names)
        role_infos = {r: infos[getattr(topics, r)] for r in present}
        out[name] = VehicleTopics(name, vcfg, topics, tuple(present), (), role_infos, name)
    return out


def _check_types(
    infos: dict[str, TopicInfo], name: str, topics: TopicMap, present: list[str], names: str
) -> None:
    for role in present:
        t = getattr(topics, role)
        info = infos[t]
        if info.schema_name not in EXPECTED_TYPES[role]:
            raise LogError(
                f"{names}: {t}: has type {info.schema_name}, expected "
                f"{' or '.join(EXPECTED_TYPES[role])} for {name}'s {role}"
            )


def _check_named_topics(
    cfg: LogsConfig,
    names: str,
    name: str,
    vcfg: VehicleConfig,
    topics: TopicMap,
    present: list[str],
) -> None:
    """A topic the config names (differs from the default template) must exist."""
    default = cfg.vehicle_defaults.topics.resolve(name)
    for role in ROLES:
        named = getattr(vcfg.topics.resolve(name), role)
        if role not in present and named != getattr(default, role):
            raise LogError(
                f"{names}: topic {named} (logs.vehicles.{name}.topics.{role}) is not in the log"
            )
    if not present:
        raise LogError(
            f"{names}: none of vehicle {name}'s topics are in the log "
            f"(expected e.g. {topics.left_image} or {topics.imu})"
        )
