"""The event log (merging frames of one event) and the divergence monitor."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.events import MIN_VISIBLE_FOR_LOST, DivergenceMonitor, EventLog

S = 1_000_000_000


def test_frames_of_one_event_merge_and_a_pause_starts_a_new_one():
    log = EventLog(merge_ns=5 * S)
    log.add(10 * S, "loop_closure", "uav1", "", 4, np.array([30 * S, 25 * S]))
    log.add(13 * S, "loop_closure", "uav1", "", 5, np.array([40 * S]))
    log.add(14 * S, "cross_vehicle", "uav1", "uav2", 2)  # another kind: its own event
    log.add(18 * S, "loop_closure", "uav1", "", 1)  # 5 s after the last frame: merged
    log.add(24 * S, "loop_closure", "uav1", "", 3)  # 6 s later: a new event
    log.add(25 * S, "loop_closure", "uav2", "", 3)  # another vehicle: its own event
    rows = [(r["event"], r["vehicle"], r["stamp_ns"] // S, r["end_stamp_ns"] // S,
             r["frames"], r["landmarks"], r["max_absence_s"]) for r in log.rows]  # fmt: skip
    assert rows == [
        ("loop_closure", "uav1", 10, 18, 3, 10, 40.0),
        ("cross_vehicle", "uav1", 14, 14, 1, 2, 0.0),
        ("loop_closure", "uav1", 24, 24, 1, 3, 0.0),
        ("loop_closure", "uav2", 25, 25, 1, 3, 0.0),
    ]


def test_divergence_needs_a_full_window_of_large_nis():
    mon = DivergenceMonitor(["a", "b"], window=4, nis_per_dof_max=10.0)
    for _ in range(3):
        assert mon.check("a", nis=400.0, dof=4, n_visible=50, n_matches=80) is None  # not full yet
    reason = mon.check("a", nis=400.0, dof=4, n_visible=50, n_matches=80)
    assert reason is not None and "median NIS per measurement 100.0 over the last 4" in reason
    assert not mon.lost_map("a")  # matching, with innovations too large: diverged
    # another vehicle's window is its own; a median below the limit is healthy
    for nis in (4.0, 400.0, 4.0, 8.0):
        assert mon.check("b", nis=nis, dof=4, n_visible=50, n_matches=80) is None


def test_a_frame_with_landmarks_in_view_and_no_match_counts_as_infinite_nis():
    mon = DivergenceMonitor(["a"], window=3, nis_per_dof_max=10.0)
    assert mon.check("a", nis=4.0, dof=4, n_visible=50, n_matches=80) is None
    # few landmarks in view, or nothing observed: no evidence either way (not recorded)
    assert (
        mon.check("a", nis=np.nan, dof=0, n_visible=MIN_VISIBLE_FOR_LOST - 1, n_matches=80) is None
    )
    assert mon.check("a", nis=np.nan, dof=0, n_visible=50, n_matches=0) is None
    assert list(mon.recent["a"]) == [1.0]
    assert mon.check("a", nis=np.nan, dof=0, n_visible=50, n_matches=80) is None
    reason = mon.check("a", nis=np.nan, dof=0, n_visible=50, n_matches=80)
    assert reason is not None and "count as infinite NIS" in reason
    assert mon.lost_map("a")  # nothing in view matched: lost, not diverged
    mon.reset("a")
    assert not mon.lost_map("a") and len(mon.recent["a"]) == 0
