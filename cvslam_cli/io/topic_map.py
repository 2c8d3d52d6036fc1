"""Which topics of a set of logs belong to which vehicle, and in which role.

Vehicles are those of `logs.vehicles` when the config names any; otherwise they are
discovered from the topic templates of `logs.vehicle_defaults` (`/{vehicle}/imu` matches
`/uav1/imu`: vehicle `uav1`). Each vehicle's topics come from its templates, an image topic
falling back to its `/compressed` variant; a topic the config names must be in the logs, a
topic may belong to one vehicle only, and each must have the message type of its role
(DESIGN.md section 4).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from cvslam_cli.config import LogsConfig, TopicMap, VehicleConfig
from cvslam_cli.errors import LogError
from cvslam_cli.io.mcap_source import LogSource, TopicInfo

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


@dataclass(frozen=True)
class LogTopics:
    """The topics of a set of logs and who they belong to.

    infos: every topic of the logs, its message count summed over them.
    logs_of: indices (into the list of sources) of the logs holding each topic.
    vehicles: the vehicles found, by name (sorted).
    role_of: (vehicle, role) of each topic mapped to a vehicle.
    """

    infos: dict[str, TopicInfo]
    logs_of: dict[str, list[int]]
    vehicles: dict[str, VehicleTopics]
    role_of: dict[str, tuple[str, str]]

    def unassigned(self) -> list[TopicInfo]:
        """The topics no vehicle uses, sorted by name."""
        return [i for t, i in sorted(self.infos.items()) if t not in self.role_of]


def map_topics(sources: Sequence[LogSource], cfg: LogsConfig, names: str) -> LogTopics:
    """The `LogTopics` of `sources` (`names`: the logs' names, for messages); LogError for a
    topic whose type differs between logs and for every mapping problem (module docstring)."""
    infos, logs_of = _merge_topics(sources)
    vehicles = _map_vehicles(infos, cfg, names)
    role_of = {v.topic(role): (v.name, role) for v in vehicles.values() for role in v.present}
    return LogTopics(infos, logs_of, vehicles, role_of)


def _merge_topics(
    sources: Sequence[LogSource],
) -> tuple[dict[str, TopicInfo], dict[str, list[int]]]:
    infos: dict[str, TopicInfo] = {}
    logs_of: dict[str, list[int]] = {}
    for i, src in enumerate(sources):
        for name, info in src.topics().items():
            old = infos.get(name)
            if old is not None and old.schema_name != info.schema_name:
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
    infos: dict[str, TopicInfo], cfg: LogsConfig, names: str
) -> dict[str, VehicleTopics]:
    chosen = dict(cfg.vehicles) if cfg.vehicles else _discover_vehicles(infos, cfg)
    out: dict[str, VehicleTopics] = {}
    owner: dict[str, str] = {}
    for name, vcfg in sorted(chosen.items()):
        topics, present = _resolve_topics(infos, name, vcfg)
        if cfg.vehicles:
            _check_named_topics(cfg, names, name, vcfg, topics, present)
        for role in present:
            t = getattr(topics, role)
            if t in owner:
                raise LogError(
                    f"{names}: topic {t} is mapped to both vehicle {owner[t]} and vehicle {name}"
                )
            owner[t] = name
            info = infos[t]
            if info.schema_name not in EXPECTED_TYPES[role]:
                raise LogError(
                    f"{names}: {t}: has type {info.schema_name}, expected "
                    f"{' or '.join(EXPECTED_TYPES[role])} for {name}'s {role}"
                )
        out[name] = VehicleTopics(name, vcfg, topics, tuple(present))
    return out


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
