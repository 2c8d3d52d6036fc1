"""Streaming ROS 2 (CDR) messages out of MCAP files.

`LogSource` is the protocol the rest of the package reads through (tests feed records
directly); `McapLogSource` implements it with the `mcap` and `mcap-ros2-support` libraries.

A file with a sound summary is read chunk by chunk in log-time order through its chunk index;
one without (a recorder that was killed, a copy cut short, a damaged summary) is read front to
back. Either way every chunk is checked against its CRC before its messages are used, and a
damaged one is skipped, the reading going on at the next sound chunk (`mcap_scan.py`); each
loss is a warning naming the bytes, the topics, the message counts and the log-time span lost.
A file in which nothing usable is left is an error naming the damage. Nothing holds more than
the chunks being read, so memory does not grow with the length of the log.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from mcap.records import Channel, Message, Schema
from mcap_ros2.decoder import DecoderFactory

from cvslam_cli.errors import LogError
from cvslam_cli.io.mcap_scan import MCAP_MAGIC, McapScan

log = logging.getLogger("cvslam")


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
        with McapScan(self.path) as scan:
            self._indexed = scan.indexed
            self._summary_problem = scan.summary_problem
        self._topics: dict[str, TopicInfo] | None = None
        self._metadata: dict[str, dict[str, str]] | None = None
        self._data_crc_checked = False
        self._decoders = DecoderFactory()

    # -- summary -----------------------------------------------------------------------

    def topics(self) -> dict[str, TopicInfo]:
        if self._topics is None:
            self._topics = {}
            if self._indexed:
                with McapScan(self.path) as scan:
                    assert scan.statistics is not None
                    counts = scan.statistics.channel_message_counts
                    for cid, ch in scan.channels.items():
                        schema = scan.schemas.get(ch.schema_id)
                        info = TopicInfo(
                            ch.topic, schema.name if schema else "", counts.get(cid, 0)
                        )
                        self._add_topic(info)
            else:
                self._scan_unindexed()
        return self._topics

    def _add_topic(self, info: TopicInfo) -> None:
        assert self._topics is not None
        old = self._topics.get(info.topic)
        if old is not None:  # several channels on one topic
            info = TopicInfo(info.topic, info.schema_name, old.message_count + info.message_count)
        self._topics[info.topic] = info

    def _scan_unindexed(self) -> None:
        """Topics, counts and metadata of a file without a sound summary, in one pass."""
        found: dict[int, tuple[Channel, Schema | None]] = {}
        counts: dict[int, int] = {}
        with McapScan(self.path) as scan:
            for schema, channel, _ in scan.stream_messages():
                found[channel.id] = (channel, schema)
                counts[channel.id] = counts.get(channel.id, 0) + 1
            self._metadata = {m.name: dict(m.metadata) for m in scan.streamed_metadata}
            self._note_damage(scan, messages_read=sum(counts.values()), log_it=False)
        for cid, (ch, schema) in found.items():
            self._add_topic(TopicInfo(ch.topic, schema.name if schema else "", counts[cid]))

    def metadata(self) -> dict[str, dict[str, str]]:
        if self._metadata is None:
            if self._indexed:
                with McapScan(self.path) as scan:
                    self._metadata = {m.name: dict(m.metadata) for m in scan.metadata()}
            else:
                self.topics()
                assert self._metadata is not None
        return self._metadata

    # -- messages ------------------------------------------------------------------------

    def messages(self, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
        """Decoded messages of `topics` (all when None), in log-time order when indexed."""
        wanted = None if topics is None else set(topics)
        if wanted is not None and not wanted:
            return
        decoders: dict[int, Any] = {}
        n_read = 0
        with McapScan(self.path) as scan:
            stream = scan.indexed_messages(wanted) if self._indexed else scan.stream_messages()
            for schema, channel, message in stream:
                if wanted is None or channel.topic in wanted:
                    n_read += 1
                    yield self._decode(schema, channel, message, decoders)
            if self._indexed and not scan.damages and not self._data_crc_checked:
                scan.check_data_crc()  # once per file: it reads the whole data section
                self._data_crc_checked = True
            self._note_damage(scan, messages_read=n_read if wanted is None else None, log_it=True)

    def _note_damage(self, scan: McapScan, *, messages_read: int | None, log_it: bool) -> None:
        """Warnings for what `scan` found damaged (logged now when `log_it`: those found at
        opening are logged by whoever reports the source's warnings); LogError when the
        damage left no message (`messages_read` 0; None for a selection of topics)."""
        texts = [d.text(self.name) for d in scan.damages]
        if texts and messages_read == 0:
            more = f"; and {len(texts) - 1} more damaged stretches" if len(texts) > 1 else ""
            raise LogError(f"{texts[0]}{more}: no usable message left in the file")
        if not self._indexed:
            texts.insert(0, f"{self.name}: {self._summary_problem}; read front to back")
        for text in texts:
            if text not in self.warnings:
                self.warnings.append(text)
                if log_it:
                    log.warning(text)

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
