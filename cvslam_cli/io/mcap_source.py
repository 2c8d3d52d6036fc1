"""Streaming ROS 2 (CDR) messages out of MCAP files.

`LogSource` is the protocol the rest of the package reads through (tests feed records
directly); `McapLogSource` implements it with the `mcap` and `mcap-ros2-support` libraries.

An indexed file is read chunk by chunk in log-time order through its summary; a file with no
usable summary (a recorder that was killed, a copy cut short) is read front to back up to the
first damaged record, and a warning says how many bytes were lost. Nothing holds more than
the chunks being read, so memory does not grow with the length of the log.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Protocol

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from cvslam_cli.errors import LogError

log = logging.getLogger("cvslam")

MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    schema_name: str
    message_count: int


@dataclass(frozen=True)
class RawMessage:
    """One decoded message. `msg` has the ROS 2 message's fields as attributes."""

    topic: str
    schema_name: str
    log_time_ns: int
    msg: Any


class LogSource(Protocol):
    """Where messages come from: an MCAP file, or a list of messages in a test."""

    name: str
    warnings: list[str]

    def topics(self) -> dict[str, TopicInfo]: ...

    def messages(self, topics: Collection[str] | None = None) -> Iterator[RawMessage]: ...

    def metadata(self) -> dict[str, dict[str, str]]: ...


class McapLogSource:
    """A ROS 2 MCAP file, opened lazily; each `messages()` call streams it once more."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.name = str(path)
        self.warnings: list[str] = []
        if not self.path.exists():
            raise LogError(f"{self.name}: file not found")
        if self.path.is_dir():
            raise LogError(
                f"{self.name}: is a directory, expected an .mcap file "
                "(for a rosbag2 folder, give the .mcap inside it)"
            )
        try:
            with self.path.open("rb") as f:
                head = f.read(len(MCAP_MAGIC))
        except OSError as exc:
            raise LogError(f"{self.name}: cannot read ({exc.strerror})") from None
        if head != MCAP_MAGIC:
            raise LogError(f"{self.name}: not an MCAP file (bad magic bytes)")
        self._size = self.path.stat().st_size
        self._indexed = self._has_summary()
        self._topics: dict[str, TopicInfo] | None = None
        self._metadata: dict[str, dict[str, str]] | None = None
        self._decoders = DecoderFactory()

    # -- summary -----------------------------------------------------------------------

    def _has_summary(self) -> bool:
        try:
            with self.path.open("rb") as f:
                summary = SeekingReader(f).get_summary()
        except (McapError, ValueError, EOFError, OSError, KeyError):
            summary = None
        return bool(summary and summary.chunk_indexes and summary.statistics)

    def topics(self) -> dict[str, TopicInfo]:
        if self._topics is None:
            if self._indexed:
                with self.path.open("rb") as f:
                    summary = SeekingReader(f).get_summary()
                    assert summary is not None and summary.statistics is not None
                    counts = summary.statistics.channel_message_counts
                    self._topics = {}
                    for cid, ch in summary.channels.items():
                        schema = summary.schemas.get(ch.schema_id)
                        info = TopicInfo(
                            ch.topic, schema.name if schema else "", counts.get(cid, 0)
                        )
                        self._add_topic(info)
            else:
                self._topics = {}
                for ch, schema, count in self._scan_channels():
                    self._add_topic(TopicInfo(ch.topic, schema.name if schema else "", count))
        return self._topics

    def _add_topic(self, info: TopicInfo) -> None:
        assert self._topics is not None
        old = self._topics.get(info.topic)
        if old is not None:  # several channels on one topic
            info = TopicInfo(info.topic, info.schema_name, old.message_count + info.message_count)
        self._topics[info.topic] = info

    def _scan_channels(self) -> list[tuple[Channel, Schema | None, int]]:
        found: dict[int, tuple[Channel, Schema | None]] = {}
        counts: dict[int, int] = {}
        with self.path.open("rb") as f:
            for schema, channel, _ in self._stream_messages(f, warn=False):
                found[channel.id] = (channel, schema)
                counts[channel.id] = counts.get(channel.id, 0) + 1
        return [(ch, schema, counts[cid]) for cid, (ch, schema) in found.items()]

    def metadata(self) -> dict[str, dict[str, str]]:
        if self._metadata is None:
            self._metadata = {}
            if self._indexed:
                with self.path.open("rb") as f:
                    for m in SeekingReader(f).iter_metadata():
                        self._metadata[m.name] = dict(m.metadata)
        return self._metadata

    # -- messages ------------------------------------------------------------------------

    def messages(self, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
        """Decoded messages of `topics` (all when None), in log-time order when indexed."""
        wanted = None if topics is None else set(topics)
        if wanted is not None and not wanted:
            return
        decoders: dict[int, Any] = {}
        with self.path.open("rb") as f:
            if self._indexed:
                reader = SeekingReader(f)
                try:
                    stream = reader.iter_messages(
                        topics=None if wanted is None else list(wanted), log_time_order=True
                    )
                    for schema, channel, message in stream:
                        yield self._decode(schema, channel, message, decoders)
                except McapError as exc:
                    raise LogError(f"{self.name}: damaged MCAP data ({exc})") from None
            else:
                for schema, channel, message in self._stream_messages(f, warn=True):
                    if wanted is None or channel.topic in wanted:
                        yield self._decode(schema, channel, message, decoders)

    def _decode(
        self, schema: Schema | None, channel: Channel, message: Message, decoders: dict[int, Any]
    ) -> RawMessage:
        dec = decoders.get(channel.id)
        if dec is None:
            if schema is None or channel.message_encoding != "cdr":
                raise LogError(
                    f"{self.name}: {channel.topic}: not a ROS 2 CDR topic "
                    f"(message encoding {channel.message_encoding!r})"
                )
            try:
                dec = self._decoders.decoder_for(channel.message_encoding, schema)
            except Exception as exc:  # the library raises several types for bad schemas
                raise LogError(
                    f"{self.name}: {channel.topic}: cannot use its schema {schema.name!r} ({exc})"
                ) from None
            if dec is None:
                raise LogError(
                    f"{self.name}: {channel.topic}: no decoder for schema "
                    f"encoding {schema.encoding!r}"
                )
            decoders[channel.id] = dec
        try:
            msg = dec(message.data)
        except Exception as exc:  # a malformed CDR payload
            raise LogError(
                f"{self.name}: {channel.topic}: message at log time "
                f"{message.log_time} cannot be decoded ({exc})"
            ) from None
        return RawMessage(channel.topic, schema.name if schema else "", message.log_time, msg)

    def _stream_messages(
        self, f: BinaryIO, *, warn: bool
    ) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """(schema, channel, message) front to back, for files with no usable summary."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        for rec in self._stream_records(f, warn=warn):
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message) and rec.channel_id in channels:
                channel = channels[rec.channel_id]
                yield schemas.get(channel.schema_id), channel, rec

    def _stream_records(self, f: BinaryIO, *, warn: bool) -> Iterator[Any]:
        """Records front to back; stops at the first damaged one with a warning."""
        good_bytes = len(MCAP_MAGIC)
        n_messages = 0
        try:
            for rec in StreamReader(f, skip_magic=False, validate_crcs=True).records:
                if isinstance(rec, Message):
                    n_messages += 1
                    good_bytes = f.tell()
                yield rec
        except (McapError, EOFError, ValueError, OSError) as exc:
            lost = self._size - good_bytes
            text = (
                f"{self.name}: truncated or damaged MCAP ({type(exc).__name__}); read "
                f"{n_messages} messages from the first {good_bytes} of {self._size} "
                f"bytes, lost the last {lost} bytes ({100.0 * lost / self._size:.1f}%)"
            )
            if warn and text not in self.warnings:
                self.warnings.append(text)
                log.warning(text)
            return
        if warn and "no summary" not in " ".join(self.warnings):
            text = f"{self.name}: no summary section (not closed cleanly); read front to back"
            self.warnings.append(text)
            log.warning(text)
