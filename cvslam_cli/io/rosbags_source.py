"""Logs the `mcap` fast path does not read, through the `rosbags` readers.

`RosbagsLogSource` implements `LogSource` (mcap_source.py) for a rosbag2 folder (its
`metadata.yaml` lists the storage files, any number of splits, MCAP or sqlite3, compressed per
file or per message), a bare sqlite3 `.db3` file and a ROS 1 `.bag`. ROS 2 messages are decoded
with the definitions stored in the bag (a `.db3` written before ROS 2 Iron stores none: then
the ROS 2 Humble definitions). ROS 1 messages are decoded with the bag's own definitions and,
where a type's field names differ from its ROS 2 version (sensor_msgs/CameraInfo: `D K R P`
against `d k r p`), migrated to the ROS 2 definition by `rosbags`' converter, so every reader
downstream sees ROS 2 field names. The ROS 1 header's `seq` is left in place (nothing reads it).

Messages are streamed one at a time in log-time order (the readers go through their indexes),
so memory does not grow with the length of the log; a file-compressed bag is decompressed by
`rosbags` into a temporary folder, on disk, while it is open.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any

from rosbags.convert.converter import migrate_message
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from cvslam_cli.errors import LogError
from cvslam_cli.io.mcap_source import RawMessage, TopicInfo

_ROS2 = get_typestore(Stores.ROS2_HUMBLE)
# what the rosbags readers raise for an unreadable bag (their own errors, or a bad file)
_READ_ERRORS = (AnyReaderError, OSError, ValueError, KeyError, EOFError, AssertionError)


def storage_kind(path: Path) -> str:
    """'rosbag2' (folder with metadata.yaml), 'sqlite3' (.db3), 'ros1' (.bag)."""
    if path.is_dir():
        return "rosbag2"
    return {".db3": "sqlite3", ".bag": "ros1"}.get(path.suffix, "unknown")


class RosbagsLogSource:
    """A rosbag2 folder, a `.db3` file or a ROS 1 `.bag`; each `messages()` call reads it
    once more (module docstring)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.name = str(path)
        self.warnings: list[str] = []
        self.kind = storage_kind(self.path)
        if self.kind == "rosbag2" and not (self.path / "metadata.yaml").is_file():
            raise LogError(
                f"{self.name}: a folder without metadata.yaml, not a rosbag2 bag (give the "
                "bag folder, or an .mcap/.db3 file inside it)"
            )
        with self._reader() as reader:
            self._topics = {
                t: TopicInfo(t, info.msgtype or "", info.msgcount)
                for t, info in reader.topics.items()
            }
            self._metadata = _bag_metadata(reader)

    @contextlib.contextmanager
    def _reader(self) -> Iterator[AnyReader]:
        """The bag opened (and closed after use); LogError when it cannot be opened."""
        try:
            reader = AnyReader([self.path], default_typestore=_ROS2)
            reader.open()
        except _READ_ERRORS as exc:
            raise LogError(f"{self.name}: cannot read this {self.kind} bag ({exc})") from None
        try:
            yield reader
        finally:
            reader.close()

    def topics(self) -> dict[str, TopicInfo]:
        return self._topics

    def metadata(self) -> dict[str, dict[str, str]]:
        return self._metadata

    def messages(self, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
        """Decoded messages of `topics` (all when None), in log-time order."""
        wanted = None if topics is None else set(topics)
        if wanted is not None and not wanted:
            return
        with self._reader() as reader:
            conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
            if not conns:
                return
            migrate = {c.msgtype: _needs_migration(reader, c.msgtype) for c in conns}
            cache: dict[str, object] = {}
            try:
                for conn, log_time_ns, raw in reader.messages(connections=conns):
                    try:
                        msg = reader.deserialize(raw, conn.msgtype)
                        if migrate[conn.msgtype]:
                            msg = migrate_message(
                                reader.typestore, _ROS2, conn.msgtype, conn.msgtype, cache, msg
                            )
                    except Exception as exc:  # a malformed payload (rosbags raises several)
                        raise LogError(
                            f"{self.name}: {conn.topic}: message at log time {log_time_ns} "
                            f"cannot be decoded ({exc})"
                        ) from None
                    yield RawMessage(conn.topic, conn.msgtype, log_time_ns, msg)
            except _READ_ERRORS as exc:
                raise LogError(f"{self.name}: damaged {self.kind} bag ({exc})") from None


def _needs_migration(reader: AnyReader, msgtype: str) -> bool:
    """Whether a ROS 1 message type must be migrated to its ROS 2 definition: it has one and
    its field names differ (ROS 2 bags are decoded with ROS 2 definitions already)."""
    return (
        not reader.is2
        and msgtype in _ROS2.fielddefs
        and not _same_names(reader.typestore, _ROS2, msgtype)
    )


def _same_names(src: Typestore, dst: Typestore, msgtype: str) -> bool:
    """Whether `msgtype` and the types it holds have the same field names in both stores
    (std_msgs/Header counts as the same: only ROS 1's `seq` differs, and nothing reads it)."""
    if msgtype == "std_msgs/msg/Header" or msgtype not in dst.fielddefs:
        return True
    s, d = src.fielddefs[msgtype][1], dst.fielddefs[msgtype][1]
    if [n for n, _ in s] != [n for n, _ in d]:
        return False
    for _, (node, sub) in s:
        inner = sub[0] if node in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (node, sub)
        if inner[0] == Nodetype.NAME and not _same_names(src, dst, str(inner[1])):
            return False
    return True


def _bag_metadata(reader: AnyReader) -> dict[str, dict[str, str]]:
    """What the bag says about itself: rosbag2's `custom_data` and ROS distribution."""
    out: dict[str, dict[str, str]] = {}
    for r in reader.readers:
        meta: Any = getattr(r, "storage", None)
        md = getattr(meta, "metadata", None)
        custom = getattr(md, "custom", None) or {}
        if custom:
            out["rosbag2_custom_data"] = {str(k): str(v) for k, v in custom.items()}
        distro = getattr(md, "ros_distro", None)
        if distro:
            out.setdefault("rosbag2", {})["ros_distro"] = str(distro)
    return out
