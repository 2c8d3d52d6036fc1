"""What was seen while streaming a set of logs, and what is wrong with it (for `cvslam info`).

`TopicStats`: per topic, counts, nominal rate, gaps, stamps going backwards, samples dropped.
`VehicleStats`: per vehicle, the stereo pairing counts and its topics' stats. `Problems`: the
problems found, each once, in the order found; an error raises `LogError` at once in strict
mode (the stages) and is only listed otherwise (`cvslam info`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from cvslam_cli.errors import LogError
from cvslam_cli.io.mcap_source import LogSource

log = logging.getLogger("cvslam")

_INTERVAL_SAMPLE = 1000  # intervals kept to estimate a topic's nominal period (median)


@dataclass(frozen=True)
class Problem:
    severity: Literal["error", "warning"]
    text: str


class Problems(list[Problem]):
    """The problems of a set of logs, each once, in the order found (a plain list to read)."""

    def __init__(self, *, strict: bool) -> None:
        super().__init__()
        self.strict = strict

    def report(
        self, severity: Literal["error", "warning"], text: str, *, log_warning: bool = True
    ) -> None:
        """Add a problem unless already listed; an error raises LogError(text) when strict.
        A new warning is also logged unless `log_warning` is False (its source logged it)."""
        if severity == "error" and self.strict:
            raise LogError(text)
        p = Problem(severity, text)
        if p not in self:
            self.append(p)
            if severity == "warning" and log_warning:
                log.warning(text)

    def add_source_warnings(self, sources: Iterable[LogSource], *, log_warning: bool) -> None:
        """The warnings the log readers collected (damaged or unindexed files)."""
        for src in sources:
            for w in src.warnings:
                self.report("warning", w, log_warning=log_warning)


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
    """One vehicle's stereo pairing counts and the stats of its topics (by topic name)."""

    stereo_pairs: int = 0
    unpaired_left: int = 0
    unpaired_right: int = 0
    max_pair_offset_ns: int = 0
    topics: dict[str, TopicStats] = field(default_factory=dict)

    def topic(self, topic: str, role: str, schema_name: str) -> TopicStats:
        """The stats of `topic`, created at its first message."""
        ts = self.topics.get(topic)
        if ts is None:
            ts = self.topics[topic] = TopicStats(topic, role, schema_name)
        return ts
