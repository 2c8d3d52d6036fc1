"""Header stamps that cannot be used, dropped and counted before any stage sees them.

A message is dropped when its stamp
- is before 1970 (negative: no output format of cvslam can carry it);
- strays more than a day from the topic's other messages, measured as the offset between
  stamp and log time against the topic's first message (one image stamped 2^31 - 1 s would
  otherwise make a 48 600 km "trajectory");
- repeats both the stamp and the content of a message the topic already had (a duplicated
  message, or the same log given twice: it would double the frames);
- and, once the reorder window has released the records, is older than one already released
  for the same stream (stamps going back further than the window can sort).

Topics are keyed by (vehicle, topic): logs bound to different vehicles may use one topic
name. `StampScreen.problems(names)` says, per topic, how many were dropped and why.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any

_DAY_NS = 86_400 * 10**9
# Messages kept per topic to find duplicates: a duplicated message, or the same message of a
# log given twice (the logs are merged by log time), comes within a few of its original.
_RECENT = 8

REASONS = {
    "before_1970": "stamped before 1970",
    "astray": "stamped more than a day away from the topic's other messages",
    "duplicate": "repeating an earlier message, stamp and content (duplicated messages?)",
    "out_of_order": "stamped earlier than a message already passed on (beyond the reorder window)",
}


@dataclass
class _Topic:
    offset_ns: int | None = None  # stamp - log time of the topic's first usable message
    recent: collections.deque[tuple[int, Any]] = field(
        default_factory=lambda: collections.deque(maxlen=_RECENT)
    )
    dropped: collections.Counter[str] = field(default_factory=collections.Counter)
    first_dropped_ns: dict[str, int] = field(default_factory=dict)


class StampScreen:
    """Decides, message by message, which stamps are usable (see the module docstring)."""

    def __init__(self) -> None:
        self._topics: dict[tuple[str, str], _Topic] = {}
        self._released: dict[tuple[str, str], int] = {}

    def _topic(self, topic: tuple[str, str]) -> _Topic:
        t = self._topics.get(topic)
        if t is None:
            t = self._topics[topic] = _Topic()
        return t

    def _drop(self, t: _Topic, reason: str, stamp_ns: int) -> bool:
        t.dropped[reason] += 1
        t.first_dropped_ns.setdefault(reason, stamp_ns)
        return False

    def arrived(self, topic: tuple[str, str], stamp_ns: int, log_time_ns: int, msg: Any) -> bool:
        """Whether the message `msg` of `topic` ((vehicle, topic name)) stamped `stamp_ns`
        (logged at `log_time_ns`) is usable."""
        t = self._topic(topic)
        if stamp_ns < 0:
            return self._drop(t, "before_1970", stamp_ns)
        offset = stamp_ns - log_time_ns
        if t.offset_ns is None:
            t.offset_ns = offset
        elif abs(offset - t.offset_ns) > _DAY_NS:
            return self._drop(t, "astray", stamp_ns)
        if any(st == stamp_ns and _same(m, msg) for st, m in t.recent):
            return self._drop(t, "duplicate", stamp_ns)
        t.recent.append((stamp_ns, msg))
        return True

    def released(self, topic: tuple[str, str], stamp_ns: int) -> bool:
        """Whether a record of `topic` ((vehicle, topic name)) released by the reorder window
        at `stamp_ns` is still in time order."""
        last = self._released.get(topic)
        if last is not None and stamp_ns < last:
            return self._drop(self._topic(topic), "out_of_order", stamp_ns)
        self._released[topic] = stamp_ns
        return True

    def problems(self, names: str) -> list[str]:
        """One line per topic and reason with drops, naming the logs, count and first stamp."""
        out = []
        for (vehicle, topic), t in sorted(self._topics.items()):
            for reason, n in sorted(t.dropped.items()):
                out.append(
                    f"{names}: vehicle {vehicle}: {topic}: dropped {n} message(s) "
                    f"{REASONS[reason]} (first at stamp {t.first_dropped_ns[reason]} ns)"
                )
        return out


def _same(a: Any, b: Any) -> bool:
    """Whether two decoded messages (of one topic, with one stamp) have the same content: the
    `data` payload of images compared as bytes, anything else by its text."""
    da, db = getattr(a, "data", None), getattr(b, "data", None)
    if da is not None and db is not None and not isinstance(da, str):
        try:
            return memoryview(da).cast("B") == memoryview(db).cast("B") and repr(a.header) == repr(
                b.header
            )
        except (TypeError, ValueError, AttributeError):  # not plain buffers: compare as text
            pass
    return repr(a) == repr(b)
