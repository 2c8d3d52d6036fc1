"""MCAP records read past damage, every loss accounted for.

The `mcap` library reads a sound file; on a damaged one it raises (or, without its CRC checks,
returns altered payloads). `McapScan` reads through the library's record parsers and CRC
checks one record at a time, so that damage costs only what it touches:

- the summary is used only when its CRC (the footer's `summary_crc`) holds; the data section's
  CRC (`DataEnd.data_section_crc`) is checked once per file and a mismatch is reported even
  when every chunk is sound (the damage is then outside the message payloads);
- every chunk is checked against its `uncompressed_crc` before any of its messages is used;
  a chunk that fails is skipped and the next one read (through the chunk index, or front to
  back by finding the next record that parses as a sound chunk);
- what a skipped chunk held is counted from its message index records (messages and log-time
  span per topic) where those survive, else from the chunk header's time span.

Each loss is a `Damage` whose `text` is the warning the user sees.
"""

from __future__ import annotations

import heapq
import os
import struct
import zlib
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Message,
    MessageIndex,
    Metadata,
    Schema,
    Statistics,
)
from mcap.stream_reader import get_chunk_data_stream

MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
_OP_MESSAGE_INDEX, _OP_CHUNK_INDEX, _OP_STATISTICS, _OP_METADATA = 0x07, 0x08, 0x0B, 0x0C
_OP_DATA_END = 0x0F
_KNOWN_OPCODES = frozenset(range(0x01, 0x10))
_RECORD_HEAD = 9  # opcode (1) + length (8)
_FOOTER_RECORD = _RECORD_HEAD + 20
_COMPRESSIONS = ("", "zstd", "lz4")
# A chunk claiming to inflate to more than this many times its stored size is damaged (zstd
# reaches ~30x on flat images; the bound keeps a flipped size field from exhausting memory).
_MAX_INFLATION = 4096
_PARSERS = {
    _OP_SCHEMA: Schema.read,
    _OP_CHANNEL: Channel.read,
    _OP_CHUNK: Chunk.read,
    _OP_MESSAGE_INDEX: MessageIndex.read,
    _OP_CHUNK_INDEX: ChunkIndex.read,
    _OP_STATISTICS: Statistics.read,
    _OP_METADATA: Metadata.read,
    _OP_DATA_END: DataEnd.read,
    _OP_FOOTER: Footer.read,
}

Triple = tuple[Schema | None, Channel, Message]


def _skip(stream: ReadDataStream, length: int) -> None:
    stream.read(length)


_INNER = {  # the records a chunk may hold (others are skipped)
    _OP_SCHEMA: lambda stream, length: Schema.read(stream),
    _OP_CHANNEL: lambda stream, length: Channel.read(stream),
    _OP_MESSAGE: Message.read,
}


@dataclass
class Lost:
    """Messages of one topic lost to one damage: how many and their log-time span."""

    count: int = 0
    first_ns: int | None = None
    last_ns: int | None = None

    def add(self, log_time_ns: int) -> None:
        self.count += 1
        self.first_ns = log_time_ns if self.first_ns is None else min(self.first_ns, log_time_ns)
        self.last_ns = log_time_ns if self.last_ns is None else max(self.last_ns, log_time_ns)


@dataclass
class Damage:
    """One damaged stretch of a file: bytes `start`..`end` (end exclusive), why it could not
    be used (`start` -1: not known), and what it held (`lost` per topic; `span_ns` when only
    the time span is known)."""

    start: int
    end: int
    what: str
    lost: dict[str, Lost] = field(default_factory=dict)
    span_ns: tuple[int, int] | None = None
    known: bool = True  # False: what it held is not known (unless `lost` or `span_ns` says)

    def text(self, name: str) -> str:
        if self.start < 0:
            where = "(place unknown)"
        elif self.end > self.start:
            where = f"at bytes {self.start}-{self.end}"
        else:
            where = f"at byte {self.start}"
        if self.lost:
            parts = [
                f"{topic} {n.count} ({_sec(n.first_ns)}-{_sec(n.last_ns)} s)"
                for topic, n in sorted(self.lost.items())
            ]
            lost = f"lost {sum(n.count for n in self.lost.values())} messages: " + ", ".join(parts)
        elif self.span_ns is not None:
            lost = (
                f"lost the messages logged {_sec(self.span_ns[0])}-{_sec(self.span_ns[1])} s "
                "(count unknown)"
            )
        elif self.known:
            lost = "no message lost"
        else:
            lost = "what it held is not known"
        return f"{name}: damaged MCAP {where} ({self.what}); {lost}"


def _sec(ns: int | None) -> str:
    return "?" if ns is None else f"{ns / 1e9:.3f}"


class _File:
    """Positional reads of one file: nothing is mapped or held, so memory stays at what the
    caller keeps (a chunk at a time), whatever the length of the file."""

    _BLOCK = 1 << 20

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_RDONLY)
        self.size = os.fstat(self._fd).st_size

    def close(self) -> None:
        os.close(self._fd)

    def read(self, pos: int, n: int) -> bytes:
        return os.pread(self._fd, n, pos) if n > 0 else b""

    def unpack(self, fmt: str, pos: int) -> tuple[Any, ...]:
        return struct.unpack(fmt, self.read(pos, struct.calcsize(fmt)))

    def crc(self, start: int, end: int) -> int:
        crc = 0
        for pos in range(start, end, self._BLOCK):
            crc = zlib.crc32(self.read(pos, min(self._BLOCK, end - pos)), crc)
        return crc

    def find(self, byte: bytes, start: int, end: int) -> int:
        """The offset of the first `byte` (one byte) in `start`..`end`, or -1."""
        for pos in range(start, end, self._BLOCK):
            i = self.read(pos, min(self._BLOCK, end - pos)).find(byte)
            if i >= 0:
                return pos + i
        return -1


class McapScan:
    """One open MCAP file; `damages` grows as its records are read."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._f = _File(path)
        self.size = self._f.size
        self.damages: list[Damage] = []
        self.summary_problem: str | None = None
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.chunk_indexes: list[ChunkIndex] = []
        self.statistics: Statistics | None = None
        self.metadata_offsets: list[int] = []
        self.streamed_metadata: list[Metadata] = []  # what `stream_messages` passed
        self._orphans: Damage | None = None  # messages whose channel was lost
        self._data_end: int | None = None  # offset of the DataEnd record
        self._indexed = self._read_summary()

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> McapScan:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def indexed(self) -> bool:
        """Whether a sound summary with chunk indexes and statistics was found."""
        return self._indexed

    # -- records ---------------------------------------------------------------------------

    def _head(self, pos: int, end: int) -> tuple[int, int] | None:
        """(opcode, body length) of the record at `pos` if it is a known one that fits."""
        if pos + _RECORD_HEAD > end:
            return None
        opcode, length = self._f.unpack("<BQ", pos)
        if opcode not in _KNOWN_OPCODES or pos + _RECORD_HEAD + length > end:
            return None
        return opcode, length

    def _parse(self, pos: int, opcode: int, length: int) -> Any:
        """The record at `pos` (None for kinds nobody here uses); raises on malformed data."""
        parser = _PARSERS.get(opcode)
        if parser is None:
            return None
        body = self._f.read(pos + _RECORD_HEAD, length)
        stream = ReadDataStream(BytesIO(body))
        if opcode == _OP_MESSAGE:
            return Message.read(stream, length)
        rec = parser(stream)
        if stream.count != length:
            raise _DamageError(f"record of {length} bytes parsed as {stream.count}")
        return rec

    def _chunk_records(self, chunk: Chunk) -> list[tuple[int, Any]]:
        """(offset in the chunk, record) of the schemas, channels and messages inside `chunk`,
        after its CRC and its framing are checked; raises when it is damaged."""
        if chunk.compression not in _COMPRESSIONS:
            raise _DamageError(f"unknown compression {chunk.compression[:16]!r}")
        if chunk.uncompressed_size > _MAX_INFLATION * max(len(chunk.data), 1):
            raise _DamageError(f"implausible uncompressed size {chunk.uncompressed_size}")
        try:
            stream, n = get_chunk_data_stream(chunk, validate_crc=True)
        except Exception as exc:  # zstd, lz4 and CRC errors alike: the chunk is lost
            raise _DamageError(_reason(exc)) from None
        if n != chunk.uncompressed_size:
            raise _DamageError(f"holds {n} bytes, its header says {chunk.uncompressed_size}")
        out: list[tuple[int, Any]] = []
        while stream.count < n:
            offset = stream.count
            if n - offset < _RECORD_HEAD:
                raise _DamageError(f"record header cut at byte {offset} of its content")
            opcode, length = stream.read1(), stream.read8()
            if stream.count + length > n:
                raise _DamageError(f"record at byte {offset} of its content runs past its end")
            start = stream.count
            try:
                rec = _INNER.get(opcode, _skip)(stream, length)
            except Exception as exc:  # a malformed record: the chunk is lost
                raise _DamageError(f"record at byte {offset}: {_reason(exc)}") from None
            if stream.count - start != length:
                raise _DamageError(f"record at byte {offset} of its content is malformed")
            if rec is not None:
                out.append((offset, rec))
        return out

    def _chunk_disagreements(
        self,
        chunk: Chunk,
        records: list[tuple[int, Any]],
        indexes: list[MessageIndex],
        ci: ChunkIndex | None = None,
    ) -> list[str]:
        """What in the chunk's header, its message index records (`indexes`; none: not
        checked) and its chunk index `ci` disagrees with its content."""
        out = []
        times = [r.log_time for _, r in records if isinstance(r, Message)]
        if times and (min(times), max(times)) != (chunk.message_start_time, chunk.message_end_time):
            out.append("its header's time span")
        if ci is not None and (
            ci.message_start_time,
            ci.message_end_time,
            ci.uncompressed_size,
            ci.compressed_size,
            ci.compression,
        ) != (
            chunk.message_start_time,
            chunk.message_end_time,
            chunk.uncompressed_size,
            len(chunk.data),
            chunk.compression,
        ):
            out.append("its chunk index")
        if indexes:
            content: dict[int, list[tuple[int, int]]] = {}
            for offset, r in records:
                if isinstance(r, Message):
                    content.setdefault(r.channel_id, []).append((r.log_time, offset))
            indexed = {ix.channel_id: sorted(ix.records) for ix in indexes}
            if indexed != {cid: sorted(v) for cid, v in content.items()}:
                out.append("its message index")
        return out

    # -- summary ---------------------------------------------------------------------------

    def _read_summary(self) -> bool:
        """Read the summary if it is sound; else note why (`summary_problem`)."""
        footer_pos = self.size - len(MCAP_MAGIC) - _FOOTER_RECORD
        if (
            footer_pos < len(MCAP_MAGIC)
            or self._f.read(self.size - len(MCAP_MAGIC), 8) != MCAP_MAGIC
        ):
            self.summary_problem = "no footer (not closed cleanly, or cut short)"
            return False
        head = self._head(footer_pos, self.size - len(MCAP_MAGIC))
        if head != (_OP_FOOTER, 20):
            self.summary_problem = "footer damaged"
            return False
        footer = self._parse(footer_pos, *head)
        if footer.summary_start == 0:
            self.summary_problem = "no summary section"
            return False
        if not len(MCAP_MAGIC) <= footer.summary_start <= footer_pos:
            self.summary_problem = f"footer damaged (summary start {footer.summary_start})"
            return False
        crc = self._f.crc(footer.summary_start, footer_pos + _RECORD_HEAD + 16)
        if footer.summary_crc not in (0, crc):
            self.summary_problem = "summary section damaged (CRC mismatch)"
            return False
        pos = footer.summary_start
        try:
            while pos < footer_pos:
                opcode, length = self._head(pos, footer_pos) or (0, 0)
                if opcode == 0:
                    raise _DamageError(f"bad record at byte {pos}")
                rec = self._parse(pos, opcode, length)
                if isinstance(rec, Schema):
                    self.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = rec
                elif isinstance(rec, ChunkIndex):
                    self.chunk_indexes.append(rec)
                elif isinstance(rec, Statistics):
                    self.statistics = rec
                elif opcode == 0x0D:  # MetadataIndex: offset of one Metadata record
                    (offset,) = self._f.unpack("<Q", pos + _RECORD_HEAD)
                    self.metadata_offsets.append(offset)
                pos += _RECORD_HEAD + length
        except Exception as exc:  # a summary that parses badly is not used at all
            self.summary_problem = f"summary section damaged ({_reason(exc)})"
            self.schemas.clear()
            self.channels.clear()
            self.chunk_indexes.clear()
            return False
        data_end = footer.summary_start - _RECORD_HEAD - 4
        if self._head(data_end, footer.summary_start) == (_OP_DATA_END, 4):
            self._data_end = data_end
        if not self.chunk_indexes or self.statistics is None:
            self.summary_problem = "summary without chunk indexes or statistics"
            return False
        return True

    def metadata(self) -> Iterator[Metadata]:
        """The Metadata records the summary indexes (sound ones only)."""
        for offset in self.metadata_offsets:
            head = self._head(offset, self.size)
            if head is None or head[0] != _OP_METADATA:
                continue
            try:
                yield self._parse(offset, *head)
            except Exception:  # a damaged metadata record is left out, like a missing one
                continue

    def check_data_crc(self) -> None:
        """Compare the data section with its CRC (indexed files); a mismatch is a damage."""
        if self._data_end is None:
            return
        head = self._head(self._data_end, self.size)
        assert head is not None
        expected = self._parse(self._data_end, *head).data_section_crc
        if expected == 0:
            return
        actual = self._f.crc(0, self._data_end)
        if actual != expected:
            self.damages.append(
                Damage(
                    len(MCAP_MAGIC),
                    self._data_end,
                    "data section CRC mismatch outside the message payloads: every message "
                    "read passed its chunk's CRC",
                )
            )

    # -- messages through the chunk index ------------------------------------------------------

    def indexed_messages(self, topics: Collection[str] | None) -> Iterator[Triple]:
        """Messages of `topics` (all when None) in log-time order, chunk by chunk through the
        chunk index; a damaged chunk is skipped and recorded."""
        wanted = (
            None
            if topics is None
            else {cid for cid, ch in self.channels.items() if ch.topic in topics}
        )
        chunks = sorted(
            (
                ci
                for ci in self.chunk_indexes
                if wanted is None
                or not ci.message_index_offsets
                or wanted & ci.message_index_offsets.keys()
            ),
            key=lambda ci: (ci.message_start_time, ci.chunk_start_offset),
        )
        heap: list[tuple[int, int, int, Triple]] = []
        i = 0
        while i < len(chunks) or heap:
            while i < len(chunks) and (not heap or chunks[i].message_start_time <= heap[0][0]):
                for j, triple in enumerate(self._indexed_chunk(chunks[i], wanted)):
                    heapq.heappush(heap, (triple[2].log_time, i, j, triple))
                i += 1
            if heap:
                yield heapq.heappop(heap)[3]

    def _indexed_chunk(self, ci: ChunkIndex, wanted: set[int] | None) -> list[Triple]:
        pos = ci.chunk_start_offset
        try:
            head = self._head(pos, self.size)
            if head is None or head[0] != _OP_CHUNK or _RECORD_HEAD + head[1] != ci.chunk_length:
                raise _DamageError("not where the chunk index points")
            chunk = self._parse(pos, *head)
            records = self._chunk_records(chunk)
        except Exception as exc:
            damage = Damage(pos, pos + ci.chunk_length, f"chunk: {_reason(exc)}")
            damage.span_ns = (ci.message_start_time, ci.message_end_time)
            self._add_indexes(damage, self._message_indexes(ci.message_index_offsets.values()))
            self.damages.append(damage)
            return []
        indexes = self._message_indexes(ci.message_index_offsets.values())
        if len(indexes) != len(ci.message_index_offsets):
            indexes = [MessageIndex(-1, [])]  # an unreadable index record disagrees
        if not self._accept(pos, chunk, records, indexes, ci):
            return []
        out = []
        for _, rec in records:
            if not isinstance(rec, Message) or (
                wanted is not None and rec.channel_id not in wanted
            ):
                continue
            channel = self.channels.get(rec.channel_id)
            if channel is None:
                continue  # not in a sound summary's channels: a writer's bug, not damage
            out.append((self.schemas.get(channel.schema_id), channel, rec))
        return out

    def _accept(
        self,
        pos: int,
        chunk: Chunk,
        records: list[tuple[int, Any]],
        indexes: list[MessageIndex],
        ci: ChunkIndex | None = None,
    ) -> bool:
        """Whether the messages of a chunk whose content parsed may be used: its metadata
        must agree with its content, or (where it does not) its CRC must vouch for it. Any
        disagreement is a damage."""
        wrong = self._chunk_disagreements(chunk, records, indexes, ci)
        if not wrong:
            return True
        end = pos + _RECORD_HEAD + _RECORD_HEAD + len(chunk.data)
        vouched = chunk.uncompressed_crc != 0
        what = f"the chunk disagrees with {', '.join(wrong)}"
        damage = Damage(pos, end, what)
        if vouched:
            damage.what += "; its messages passed its CRC and are used"
        else:
            damage.what += " and has no CRC: its messages are not used"
            for _, rec in records:
                if isinstance(rec, Message):
                    self._lost_message(damage, rec.channel_id, rec.log_time)
        self.damages.append(damage)
        return vouched

    def _message_indexes(self, offsets: Collection[int]) -> list[MessageIndex]:
        """The message index records at `offsets` that can be read."""
        out = []
        for offset in offsets:
            head = self._head(offset, self.size)
            if head is None or head[0] != _OP_MESSAGE_INDEX:
                continue
            try:
                out.append(self._parse(offset, *head))
            except Exception:  # an unreadable index: left out (and so it disagrees)
                continue
        return out

    def _add_indexes(self, damage: Damage, indexes: list[MessageIndex]) -> None:
        """Count in `damage.lost` the messages `indexes` list."""
        for index in indexes:
            for log_time, _ in index.records:
                self._lost_message(damage, index.channel_id, log_time)

    def _lost_message(self, damage: Damage, channel_id: int, log_time_ns: int) -> None:
        channel = self.channels.get(channel_id)
        topic = channel.topic if channel else f"channel {channel_id}"
        damage.lost.setdefault(topic, Lost()).add(log_time_ns)

    # -- messages front to back -----------------------------------------------------------------

    def stream_messages(self) -> Iterator[Triple]:
        """Every message front to back (file order), for files without a sound summary;
        damaged records are skipped up to the next sound chunk and recorded. A chunk's
        messages are used once the message index records after it are checked."""
        schemas: dict[int, Schema] = {}
        pos, end = len(MCAP_MAGIC), self.size
        last_damage: Damage | None = None  # message indexes right after it count its losses
        pending: tuple[int, Chunk, list[tuple[int, Any]]] | None = None
        indexes: list[MessageIndex] = []
        while pos < end:
            start, head, rec = pos, self._head(pos, end), None
            try:
                if head is None:
                    raise _DamageError(self._bad_head(pos, end))
                rec = self._parse(pos, *head)
                records = self._chunk_records(rec) if head[0] == _OP_CHUNK else [(0, rec)]
                pos += _RECORD_HEAD + head[1]
            except Exception as exc:
                if pending is not None:
                    yield from self._use_chunk(pending, indexes, schemas)
                    pending = None
                after = start + _RECORD_HEAD + head[1] if head is not None else end
                # go on right after it when a record starts there (its message index records
                # then count what it held), else at the next sound chunk
                pos = after if self._head(after, end) else self._next_chunk(start + 1, end)
                kind = "chunk" if self._f.read(start, 1) == bytes([_OP_CHUNK]) else "record"
                last_damage = Damage(
                    start, pos, exc.args[0] if head is None else f"{kind}: {_reason(exc)}"
                )
                if kind == "chunk":
                    last_damage.span_ns = self._chunk_span(start, end)
                last_damage.known = False
                self.damages.append(last_damage)
                continue
            if isinstance(rec, MessageIndex):
                if pending is not None:
                    indexes.append(rec)
                elif last_damage is not None:
                    self._add_indexes(last_damage, [rec])
                continue
            if pending is not None:
                yield from self._use_chunk(pending, indexes, schemas)
                pending = None
            last_damage = None
            if isinstance(rec, Chunk):
                pending, indexes = (start, rec, records), []
            elif isinstance(rec, DataEnd):
                if not self.damages:
                    self._data_end = start
                    self.check_data_crc()
                break  # the summary that follows is not sound (else this is not called)
            elif isinstance(rec, Footer):
                break
            elif isinstance(rec, Metadata):
                self.streamed_metadata.append(rec)
            else:
                yield from self._use(records, schemas)
        if pending is not None:
            yield from self._use_chunk(pending, indexes, schemas)

    def _use_chunk(
        self,
        pending: tuple[int, Chunk, list[tuple[int, Any]]],
        indexes: list[MessageIndex],
        schemas: dict[int, Schema],
    ) -> Iterator[Triple]:
        pos, chunk, records = pending
        for _, r in records:  # its channels name the topics of what it may lose
            if isinstance(r, Channel):
                self.channels[r.id] = r
        if self._accept(pos, chunk, records, indexes):
            yield from self._use(records, schemas)

    def _use(self, records: list[tuple[int, Any]], schemas: dict[int, Schema]) -> Iterator[Triple]:
        """The messages among `records`, schemas and channels noted on the way."""
        for _, r in records:
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                self.channels[r.id] = r
            elif isinstance(r, Message):
                channel = self.channels.get(r.channel_id)
                if channel is not None and (channel.schema_id == 0 or channel.schema_id in schemas):
                    yield schemas.get(channel.schema_id), channel, r
                    continue
                if self._orphans is None:
                    self._orphans = Damage(-1, -1, "its Channel or Schema records were lost")
                    self.damages.append(self._orphans)
                self._lost_message(self._orphans, r.channel_id, r.log_time)

    def _bad_head(self, pos: int, end: int) -> str:
        """Why the record header at `pos` is not usable."""
        if end - pos < _RECORD_HEAD:
            return f"file truncated: ends inside a record header at byte {pos}"
        opcode, length = self._f.unpack("<BQ", pos)
        if opcode not in _KNOWN_OPCODES:
            return f"unknown record opcode 0x{opcode:02x}"
        kind = "chunk" if opcode == _OP_CHUNK else "record"
        if pos + _RECORD_HEAD + length > self.size:
            return f"file truncated: a {kind} of {length} bytes at byte {pos} runs past its end"
        return f"a {kind} of {length} bytes at byte {pos} runs past the data section"

    def _chunk_span(self, pos: int, end: int) -> tuple[int, int] | None:
        """The log-time span a chunk header at `pos` claims, when it is there to read."""
        if pos + _RECORD_HEAD + 16 > end:
            return None
        start, stop = self._f.unpack("<QQ", pos + _RECORD_HEAD)
        return (start, stop) if start <= stop else None

    def _next_chunk(self, pos: int, end: int) -> int:
        """The offset of the next record from `pos` on that parses as a sound chunk (`end`
        when there is none)."""
        while True:
            pos = self._f.find(bytes([_OP_CHUNK]), pos, end)
            if pos < 0:
                return end
            head = self._head(pos, end)
            if head is not None and head[0] == _OP_CHUNK and self._plausible_chunk(pos, head[1]):
                try:
                    self._chunk_records(self._parse(pos, *head))
                    return pos
                except Exception:  # not a sound chunk: keep looking
                    pass
            pos += 1

    def _plausible_chunk(self, pos: int, length: int) -> bool:
        """A cheap test of a chunk header's internal consistency before parsing it."""
        body = pos + _RECORD_HEAD
        if length < 40:
            return False
        start, stop, _size, _crc, n = self._f.unpack("<QQQII", body)
        if start > stop or n > 4:
            return False
        if 32 + n + 8 > length:
            return False
        comp = self._f.read(body + 32, n)
        (n_data,) = self._f.unpack("<Q", body + 32 + n)
        return comp in (b"", b"zstd", b"lz4") and 32 + n + 8 + n_data == length


class _DamageError(ValueError):
    """A record found damaged; its text is the reason shown to the user."""


def _reason(exc: BaseException) -> str:
    """A short, one-line reason from a library exception."""
    if isinstance(exc, _DamageError):
        return str(exc)
    if type(exc).__name__ == "CRCValidationError":
        return "CRC mismatch"
    text = str(exc).splitlines()[0][:120] if str(exc) else ""
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
