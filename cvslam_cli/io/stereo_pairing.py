"""Left and right images of each vehicle paired into `StereoFrame`s, as they stream by.

Images arrive in stamp order, so when one with stamp t arrives, queued images (either side)
older than t - tolerance can never be paired and are counted as unpaired; the oldest queued
image of the other side within the tolerance is its partner. Memory is bounded by the
tolerance, not by the log length.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator

from cvslam_cli.io.log_stats import VehicleStats
from cvslam_cli.records.log import ImageRecord, Record, StereoFrame


class StereoPairer:
    """Pairs left/right images of each vehicle arriving in stamp order (module docstring);
    other records pass through. Counts pairs, unpaired images and the largest left/right
    stamp offset in `stats`. `role_of`: (vehicle, topic) -> role of each image topic."""

    def __init__(
        self, tolerance_ns: int, stats: dict[str, VehicleStats], role_of: dict[tuple[str, str], str]
    ) -> None:
        self.tol = tolerance_ns
        self.stats = stats
        self.role_of = role_of
        self.queues: dict[tuple[str, str], deque[ImageRecord]] = {}

    def _unpaired(self, vehicle: str, side: str, n: int = 1) -> None:
        vs = self.stats[vehicle]
        setattr(vs, f"unpaired_{side}", getattr(vs, f"unpaired_{side}") + n)

    def push(self, rec: Record | ImageRecord) -> Iterator[Record]:
        """The records `rec` completes: itself when not an image, a `StereoFrame` when it is
        the partner of a queued image, nothing when it is queued."""
        if not isinstance(rec, ImageRecord):
            yield rec
            return
        vehicle = rec.vehicle
        role = self.role_of[(vehicle, rec.topic)]
        side = role.removesuffix("_image")
        other_side = "right" if side == "left" else "left"
        for s in (side, other_side):
            q = self.queues.setdefault((vehicle, s), deque())
            while q and q[0].stamp_ns < rec.stamp_ns - self.tol:
                q.popleft()
                self._unpaired(vehicle, s)
        other = self.queues[(vehicle, other_side)]
        if not other:
            self.queues[(vehicle, side)].append(rec)
            return
        mate = other.popleft()
        left, right = (rec, mate) if side == "left" else (mate, rec)
        vs = self.stats[vehicle]
        vs.stereo_pairs += 1
        vs.max_pair_offset_ns = max(vs.max_pair_offset_ns, abs(right.stamp_ns - left.stamp_ns))
        yield StereoFrame(vehicle, left.stamp_ns, left, right)

    def finish(self) -> None:
        """Count the images still queued as unpaired (the end of the stream)."""
        for (vehicle, side), q in self.queues.items():
            self._unpaired(vehicle, side, len(q))
            q.clear()
