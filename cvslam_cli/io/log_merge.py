"""Several logs read as one stream, in header-stamp order, with bounded memory.

The messages of the logs are merged by log time (each log is read in log-time order), then
put in header-stamp order by a reorder window: a record is released once a record at least
`window_ns` newer has been seen. Stamps that arrive later than the window stay out of order
(the statistics count them); memory is bounded by the window, not by the log length.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Collection, Iterator, Sequence
from typing import Any

from cvslam_cli.io.mcap_source import LogSource, RawMessage


def merged_messages(
    sources: Sequence[LogSource], wanted: dict[int, Collection[str]]
) -> Iterator[tuple[int, RawMessage]]:
    """(log index, message) of the topics `wanted` from each log (log index -> its topics),
    merged by log time."""
    streams = [_tagged(i, sources[i], ts) for i, ts in sorted(wanted.items()) if ts]
    if len(streams) == 1:
        yield from streams[0]
    else:
        yield from heapq.merge(*streams, key=lambda r: r[1].log_time_ns)


def _tagged(i: int, source: LogSource, topics: Collection[str]) -> Iterator[tuple[int, RawMessage]]:
    for raw in source.messages(list(topics)):
        yield i, raw


class ReorderWindow:
    """Releases records (anything with `stamp_ns`) in stamp order once the newest record seen
    is `window_ns` ahead of them; ties keep their arrival order. `peak` is the most records
    held at once."""

    def __init__(self, window_ns: int) -> None:
        self.window_ns = window_ns
        self._heap: list[tuple[int, int, Any]] = []
        self._counter = itertools.count()
        self._newest = -(2**63)
        self.peak = 0

    def push(self, rec: Any) -> None:
        """Hold `rec` until the window has passed it (`released`)."""
        heapq.heappush(self._heap, (rec.stamp_ns, next(self._counter), rec))
        self.peak = max(self.peak, len(self._heap))
        self._newest = max(self._newest, rec.stamp_ns)

    def released(self) -> Iterator[Any]:
        """The records the window has passed (older than the newest by `window_ns` or more),
        oldest first."""
        heap = self._heap
        while heap and heap[0][0] <= self._newest - self.window_ns:
            yield heapq.heappop(heap)[2]

    def drain(self) -> Iterator[Any]:
        """Every record still held, oldest first (the end of the stream)."""
        while self._heap:
            yield heapq.heappop(self._heap)[2]
