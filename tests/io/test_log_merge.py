"""Logs merged by log time; records put in stamp order within the reorder window."""

from __future__ import annotations

from dataclasses import dataclass, field

from cvslam_cli.io.log_merge import ReorderWindow, merged_messages
from cvslam_cli.io.mcap_source import RawMessage


@dataclass
class _Messages:
    """A log of (topic, log time) messages, in log-time order."""

    log: list[tuple[str, int]]
    asked: list[set[str]] = field(default_factory=list)

    def messages(self, topics):
        self.asked.append(set(topics))
        return (RawMessage(t, "", ns, None) for t, ns in self.log if t in topics)


def test_logs_merged_by_log_time_each_asked_for_its_own_topics():
    a = _Messages([("/a", 1), ("/c", 4), ("/a", 6)])
    b = _Messages([("/b", 2), ("/b", 5)])
    idle = _Messages([("/d", 3)])
    out = list(merged_messages([a, b, idle], {0: ["/a"], 1: ["/b"], 2: []}))
    assert [(i, m.topic, m.log_time_ns) for i, m in out] == [
        (0, "/a", 1),
        (1, "/b", 2),
        (1, "/b", 5),
        (0, "/a", 6),
    ]
    assert (a.asked, b.asked, idle.asked) == ([{"/a"}], [{"/b"}], [])


@dataclass
class _Stamped:
    stamp_ns: int
    tag: str = ""


def test_reorder_window_releases_in_stamp_order_once_the_window_has_passed():
    window = ReorderWindow(10)
    released = []
    for rec in [_Stamped(5), _Stamped(0), _Stamped(8), _Stamped(12), _Stamped(15, "a")]:
        window.push(rec)
        released.append([r.stamp_ns for r in window.released()])
    assert released == [[], [], [], [0], [5]]  # 12 releases <= 2, 15 releases <= 5
    window.push(_Stamped(9))  # late, but still within the window: put in order
    assert list(window.released()) == []
    assert [(r.stamp_ns, r.tag) for r in window.drain()] == [(8, ""), (9, ""), (12, ""), (15, "a")]
    assert window.peak == 4
