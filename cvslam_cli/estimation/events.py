"""What the filter's loop reports besides its estimates: the event log (loop closures,
cross-vehicle re-observations, joint initialisations, localisations, divergence), the
divergence monitor, and the timeline row of a frame.

Events: frames of the same vehicle with the same kind of event (and the same other vehicles)
less than `merge_ns` apart are one event: one loop closure or one encounter, counted over its
frames.

Divergence: the normalised innovation squared per measurement (NIS / dof, 1 on average for a
consistent filter), its median over the vehicle's last `window` updates (robust to a single
bad frame); above `nis_per_dof_max`, or any non-finite number in its state, the run stops and
says when. The chi-square gate keeps gross innovations out of the NIS, so a frame where at
least `MIN_VISIBLE_FOR_LOST` landmarks are predicted in view but none matches inside its
window (the filter has lost its map) counts as infinite NIS. A vehicle whose median is
infinite has lost the map rather than diverged: it is relocalised (`relocalisation.py`),
when that is on; a finite median above the limit (innovations too large while matching: a
filter whose noise settings are wrong) stops the run.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from cvslam_cli.records.arrays import I64

# a frame with at least this many landmarks predicted in view and none matched counts as an
# update with infinite NIS for divergence detection (the filter has lost its map)
MIN_VISIBLE_FOR_LOST = 10


class EventLog:
    """Event rows (dicts: stamp_ns, end_stamp_ns, event, vehicle, other_vehicles, frames,
    landmarks, max_absence_s, detail) in the order they started, merged (module docstring)."""

    def __init__(self, merge_ns: int) -> None:
        self.merge_ns = merge_ns
        self.rows: list[dict[str, Any]] = []
        self._open: dict[tuple[str, str, str], dict[str, Any]] = {}

    def add(
        self,
        t_ns: int,
        kind: str,
        vehicle: str,
        others: str,
        count: int,
        absent_ns: I64 | None = None,
        detail: str = "",
    ) -> None:
        """An event of `kind` at t_ns for `vehicle` with the vehicles `others` (';'-joined),
        involving `count` landmarks absent up to max(absent_ns) before."""
        absence = (
            float(np.max(absent_ns)) * 1e-9 if absent_ns is not None and len(absent_ns) else 0.0
        )
        key = (kind, vehicle, others)
        last = self._open.get(key)
        if last is not None and t_ns - last["end_stamp_ns"] <= self.merge_ns:
            last["end_stamp_ns"] = t_ns
            last["frames"] += 1
            last["landmarks"] += count
            last["max_absence_s"] = max(last["max_absence_s"], absence)
            return
        row = {
            "stamp_ns": t_ns,
            "end_stamp_ns": t_ns,
            "event": kind,
            "vehicle": vehicle,
            "other_vehicles": others,
            "frames": 1,
            "landmarks": count,
            "max_absence_s": absence,
            "detail": detail,
        }
        self.rows.append(row)
        self._open[key] = row


@dataclass(frozen=True)
class Divergence:
    vehicle: str
    stamp_ns: int
    reason: str


class DivergenceMonitor:
    """The median NIS per measurement over each vehicle's last `window` updates (module
    docstring)."""

    def __init__(self, vehicles: list[str], window: int, nis_per_dof_max: float) -> None:
        self.nis_per_dof_max = nis_per_dof_max
        self.recent: dict[str, deque[float]] = {v: deque(maxlen=window) for v in vehicles}

    def lost_map(self, vehicle: str) -> bool:
        """Whether `vehicle`'s median NIS is infinite: most of its recent frames matched
        nothing in view (it lost the map), rather than matched with innovations too large
        (a filter whose noise settings are wrong)."""
        recent = self.recent[vehicle]
        return bool(recent) and bool(np.isinf(np.median(recent)))

    def reset(self, vehicle: str) -> None:
        """Forget `vehicle`'s updates (it was lost and starts anew: `relocalisation.py`)."""
        self.recent[vehicle].clear()

    def check(
        self, vehicle: str, nis: float, dof: int, n_visible: int, n_matches: int
    ) -> str | None:
        """Add a frame's update (NIS with `dof` degrees of freedom; dof 0: no update although
        n_visible landmarks were predicted in view and n_matches stereo matches observed)
        and say why the vehicle diverged, if it did."""
        recent = self.recent[vehicle]
        if dof:
            recent.append(nis / dof)
        elif n_visible >= MIN_VISIBLE_FOR_LOST and n_matches:
            # landmarks in view, observations there, none inside its window: the
            # innovations are beyond the gate, i.e. larger than any NIS recorded
            recent.append(np.inf)
        if not (dof or np.isinf(recent[-1] if recent else 0.0)):
            return None
        median_nis = float(np.median(recent))
        if not (len(recent) == recent.maxlen and median_nis > self.nis_per_dof_max):
            return None
        return (
            f"median NIS per measurement {median_nis:.1f} over the last "
            f"{len(recent)} updates (1 expected, limit {self.nis_per_dof_max:g})"
            + (
                "; frames where no landmark predicted in view matched inside its "
                "window count as infinite NIS"
                if np.isinf(median_nis)
                else ""
            )
        )
