"""Map management: the book of every landmark ever mapped, and which are in the filter state.

Each landmark has a global id (in order of creation) and keeps, whether it is in the state
or not: its descriptor (from the frame that created it), which vehicles observed it (a
bitmask), how often, when it was first and last seen (per vehicle), and its estimate. The
state holds at most `settings.landmark_bound`; when a frame needs room, landmarks are evicted
(marginalised out, `JointState.remove_landmarks`) and keep their last estimate: the nav-frame
mean and marginal covariance at eviction (`cov_nav_m2`; their cross-covariance with the
state is dropped, as marginalisation drops it), and when they left (`evicted_ns`). They stay
in the book for the output map and the map file (`archive.py`) and for re-activation
(`reactivation.py`), which brings one back into the state when a vehicle sees it again.

Eviction rule (keep what is most useful for later re-observation): landmarks observed in the
current frame are never evicted, and those observed or created in another vehicle's latest
frame (or within `fuse.map.others_tracking_s` before it: a frame updates only some of the
landmarks it sees) go last (that vehicle is tracking them and has not had its next frame
yet: with several vehicles adding landmarks in turn, evicting them would make each vehicle
evict the others' landmarks before they are ever tracked; with one vehicle this group is
empty);
within each group the ones with the fewest observations go first (a landmark tracked over
many frames is distinctive and well placed, and is the one a loop closure or another vehicle
will find again; one seen once or twice rarely is), ties broken by the largest position
uncertainty (the least a re-observation would correct).

Viewing directions: each landmark keeps the sum of the unit vectors from it to the cameras
that observed it. A landmark is only expected in a view whose direction is within a maximum
angle of their mean (as ORB-SLAM does): a point on a wall or a box is not visible from behind
it, nor recognisable at a much more oblique angle, so a vehicle looking at the other side of
an obstacle (as two ground robots driving towards each other do) must not count it as
predicted in view.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import DESCRIPTOR_SIZE
from cvslam_cli.records.landmark_archive import NEVER_NS, LandmarkArchive

NEVER = NEVER_NS


class LandmarkBook:
    """Per-landmark records, indexed by global landmark id; `slot_ids` (L,) maps the state's
    landmark slots to ids."""

    def __init__(self, n_vehicles: int, capacity: int = 1024) -> None:
        self.n_vehicles = n_vehicles
        self.count = 0
        self.desc = np.zeros((capacity, DESCRIPTOR_SIZE), dtype=np.uint8)
        self.observers = np.zeros(capacity, dtype=np.int64)  # bit i: vehicle i
        # per vehicle, the bits of the vehicles linked to it by landmarks observed by both, or
        # through others (itself included): the team's groups, one gauge each (gauge.py)
        self.linked = np.array([1 << i for i in range(n_vehicles)], dtype=np.int64)
        self.n_observations = np.zeros(capacity, dtype=np.int64)
        self.first_seen_ns = np.zeros(capacity, dtype=np.int64)
        self.last_seen_ns = np.full((capacity, n_vehicles), NEVER, dtype=np.int64)
        self.true_id = np.full(capacity, -1, dtype=np.int64)
        self.p_nav_m = np.zeros((capacity, 3))
        self.cov_nav_m2 = np.zeros((capacity, 3, 3))
        self.evicted_ns = np.full(capacity, NEVER, dtype=np.int64)  # last eviction
        self.reactivations = np.zeros(capacity, dtype=np.int64)
        self.view_sum = np.zeros((capacity, 3))
        # the sum of ln(distance / m) from the landmark to the cameras that observed it (nan:
        # unknown, a prior map's landmark: the map file does not keep it)
        self.log_distance_sum = np.zeros(capacity)
        # gauge rows (nav frame) at eviction, when the state carries a gauge (gauge.py)
        self.gauge_nav = np.zeros((capacity, 3, 4))
        # mapped by a vehicle whose pose had gone wrong: position unknown (relocalisation.py)
        self.forgotten = np.zeros(capacity, dtype=bool)
        self.slot_ids = np.zeros(0, dtype=np.int64)

    def _grow(self, need: int) -> None:
        cap = len(self.n_observations)
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name in (
            "desc",
            "observers",
            "n_observations",
            "first_seen_ns",
            "last_seen_ns",
            "true_id",
            "p_nav_m",
            "cov_nav_m2",
            "evicted_ns",
            "reactivations",
            "view_sum",
            "log_distance_sum",
            "gauge_nav",
            "forgotten",
        ):
            old = getattr(self, name)
            never = name in ("last_seen_ns", "evicted_ns")
            fill = NEVER if never else (-1 if name == "true_id" else 0)
            arr = np.full((new_cap, *old.shape[1:]), fill, dtype=old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def add(
        self,
        desc: NDArray[np.uint8],
        vehicle: int,
        stamp_ns: int,
        true_id: I64,
        view_dir: F64,
        distance_m: F64 | None = None,
    ) -> I64:
        """Register k new landmarks (appended to the state's slots), seen along the unit
        vectors view_dir (k, 3) (landmark to camera, nav frame) from `distance_m` (k,) (None:
        unknown). Returns their ids."""
        k = len(desc)
        ids = np.arange(self.count, self.count + k)
        self._grow(self.count + k)
        self.desc[ids] = desc
        self.observers[ids] = 1 << vehicle
        self.n_observations[ids] = 1
        self.first_seen_ns[ids] = stamp_ns
        self.last_seen_ns[ids, vehicle] = stamp_ns
        self.true_id[ids] = true_id
        self.view_sum[ids] = view_dir
        self.log_distance_sum[ids] = np.nan if distance_m is None else np.log(distance_m)
        self.count += k
        self.slot_ids = np.concatenate([self.slot_ids, ids])
        return ids

    def observe(
        self, ids: I64, vehicle: int, stamp_ns: int, view_dir: F64, distance_m: F64
    ) -> None:
        """Landmarks `ids` (k,) observed by `vehicle` along view_dir (k, 3) (unit vectors,
        landmark to camera) from `distance_m` (k,)."""
        self.n_observations[ids] += 1
        self.observers[ids] |= 1 << vehicle
        if len(ids):
            self._link(int(np.bitwise_or.reduce(self.observers[ids])))
        self.last_seen_ns[ids, vehicle] = stamp_ns
        self.view_sum[ids] += view_dir
        self.log_distance_sum[ids] += np.log(distance_m)

    def _link(self, bits: int) -> None:
        """The vehicles of `bits` and those linked to them form one group from now on."""
        group = 0
        for i in range(self.n_vehicles):
            if bits >> i & 1:
                group |= int(self.linked[i])
        for i in range(self.n_vehicles):
            if group >> i & 1:
                self.linked[i] = group

    def group(self, observers: int) -> int:
        """The bits of the vehicles linked to those of `observers` (one group: a landmark's
        observers are linked by it); every vehicle for none (a prior map's landmark)."""
        if not observers:
            return (1 << self.n_vehicles) - 1
        return int(self.linked[(observers & -observers).bit_length() - 1])

    def ids_seen_from(self, ids: I64, view_dir: F64, min_cos: float) -> NDArray[np.bool_]:
        """(k,) whether landmarks `ids` (k,), in the state or not, are viewed along view_dir
        (k, 3) (unit vectors) within the maximum angle (cos >= min_cos) of their mean viewing
        direction."""
        mean = self.view_sum[np.asarray(ids, dtype=np.int64)]
        norm = np.linalg.norm(mean, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.einsum("ij,ij->i", mean, view_dir) / norm
        return (norm == 0) | (cos >= min_cos)

    def ids_viewable(
        self,
        ids: I64,
        vehicle: int,
        view_dir: F64,
        distance_m: F64,
        min_cos: float,
        max_ratio: float,
    ) -> NDArray[np.bool_]:
        """(k,) whether `vehicle`, along view_dir (k, 3) (unit vectors) at `distance_m` (k,)
        from landmarks `ids` (k,), may look for them: `ids_seen_from` and
        `ids_within_distance` (module docstring of association.py)."""
        return self.ids_seen_from(ids, view_dir, min_cos) & self.ids_within_distance(
            ids, vehicle, distance_m, max_ratio
        )

    def unseen_by(self, ids: I64, vehicle: int) -> NDArray[np.bool_]:
        """(k,) whether `vehicle` has never observed landmarks `ids` (k,) (another vehicle's,
        to it)."""
        return self.last_seen_ns[ids, vehicle] == NEVER

    def ids_within_distance(
        self, ids: I64, vehicle: int, distance_m: F64, max_ratio: float
    ) -> NDArray[np.bool_]:
        """(k,) whether `vehicle`, at `distance_m` (k,) from landmarks `ids` (k,), may look
        for them: a landmark it has observed, or one whose viewing distance (the geometric
        mean of its observations') is unknown, always; any other within a factor
        `max_ratio` of that distance (0: no limit). Module docstring of association.py."""
        ids = np.asarray(ids, dtype=np.int64)
        if max_ratio <= 0:
            return np.ones(len(ids), dtype=bool)
        mean_log = self.log_distance_sum[ids] / np.maximum(self.n_observations[ids], 1)
        with np.errstate(invalid="ignore"):
            far = np.abs(np.log(distance_m) - mean_log) > np.log(max_ratio)
        return ~self.unseen_by(ids, vehicle) | ~far

    def eviction_order(
        self, protected_slots: I64, trace_cov: F64, latest_frame_ns: I64, tracking_ns: int = 0
    ) -> I64:
        """Slots that may be evicted, most evictable first (module docstring). trace_cov (L,):
        trace of each landmark's covariance; latest_frame_ns (n_vehicles,): each other
        vehicle's latest frame stamp (NEVER for the vehicle evicting, and before a first
        frame); tracking_ns: a landmark another vehicle observed within this long before its
        latest frame is one it is tracking (0: in that frame only)."""
        L = len(self.slot_ids)
        ok = np.ones(L, dtype=bool)
        ok[np.asarray(protected_slots, dtype=np.int64)] = False
        cand = np.flatnonzero(ok)
        ids = self.slot_ids[cand]
        latest = np.asarray(latest_frame_ns, dtype=np.int64)[None, :]
        tracked = np.any(
            (self.last_seen_ns[ids] >= latest - tracking_ns) & (latest != NEVER), axis=1
        )
        return cand[np.lexsort((-trace_cov[cand], self.n_observations[ids], tracked))]

    def store_estimates(self, slots: I64, p_nav_m: F64, cov: F64) -> None:
        """Record the current nav-frame estimate (k, 3) and marginal covariance (k, 3, 3) of
        the landmarks in slots."""
        ids = self.slot_ids[np.asarray(slots, dtype=np.int64)]
        self.p_nav_m[ids] = p_nav_m
        self.cov_nav_m2[ids] = cov

    @property
    def std_m(self) -> F64:
        """(capacity, 3) standard deviations of the stored estimates (sqrt of the diagonal)."""
        return np.sqrt(np.maximum(np.diagonal(self.cov_nav_m2, axis1=1, axis2=2), 0.0))

    def keep_slots(self, kept: I64) -> None:
        """After `JointState.remove_landmarks`: slot i now holds old slot kept[i]."""
        self.slot_ids = self.slot_ids[kept]

    def evict(
        self, slots: I64, p_nav_m: F64, cov: F64, stamp_ns: int, gauge: F64 | None = None
    ) -> None:
        """Landmarks in `slots` leave the state at stamp_ns with their estimate (k, 3),
        marginal covariance (k, 3, 3) and gauge rows (k, 3, g) if the state has a gauge
        (call before `JointState.remove_landmarks` and `keep_slots`)."""
        self.store_estimates(slots, p_nav_m, cov)
        ids = self.slot_ids[np.asarray(slots, dtype=np.int64)]
        self.evicted_ns[ids] = stamp_ns
        if gauge is not None:
            self.gauge_nav[ids, :, : gauge.shape[2]] = gauge

    def known(self, ids: I64, max_std_m: float) -> NDArray[np.bool_]:
        """(k,) whether each landmark of `ids` has a stored position known to `max_std_m`
        (the trace of its covariance at most 3 max_std_m^2) and was not forgotten."""
        with np.errstate(invalid="ignore"):
            trace = np.trace(self.cov_nav_m2[ids], axis1=1, axis2=2)
            return np.isfinite(trace) & (trace <= 3 * max_std_m**2) & ~self.forgotten[ids]

    def forget(self, ids: I64, cov: F64) -> None:
        """Landmarks `ids` (out of the state) were mapped from a pose gone wrong: their
        stored estimate stays, with covariance `cov` (3, 3), and they are not used again."""
        self.forgotten[ids] = True
        self.cov_nav_m2[ids] = cov

    def in_state_mask(self) -> NDArray[np.bool_]:
        """(count,) whether each landmark is in the state now."""
        mask = np.zeros(self.count, dtype=bool)
        mask[self.slot_ids] = True
        return mask

    def readmit(self, ids: I64) -> None:
        """Landmarks `ids` (out of the state) were appended to the state's slots again
        (`reactivation.py`)."""
        ids = np.asarray(ids, dtype=np.int64)
        self.reactivations[ids] += 1
        self.slot_ids = np.concatenate([self.slot_ids, ids])

    def archive(self, names: list[str], coordinates: str) -> LandmarkArchive:
        """Every landmark in the book (`records.landmark_archive`), vehicle i named names[i];
        the stored estimates must be current (`store_estimates` of the state's landmarks)."""
        n = self.count
        return LandmarkArchive(
            vehicles=tuple(names),
            landmark_id=np.arange(n),
            true_id=self.true_id[:n],
            p_nav_m=self.p_nav_m[:n],
            cov_nav_m2=self.cov_nav_m2[:n],
            descriptor=self.desc[:n],
            view_dir_sum_nav=self.view_sum[:n],
            first_seen_ns=self.first_seen_ns[:n],
            last_seen_ns=self.last_seen_ns[:n],
            n_observations=self.n_observations[:n],
            in_state=self.in_state_mask(),
            evicted_ns=self.evicted_ns[:n],
            reactivations=self.reactivations[:n],
            coordinates=coordinates,
        )

    def other_observers(self, ids: I64, vehicle: int, names: list[str]) -> str:
        """The vehicles (named `names`) other than `vehicle` that observed any of `ids`."""
        bits = int(np.bitwise_or.reduce(self.observers[ids])) & ~(1 << vehicle)
        return ";".join(n for i, n in enumerate(names) if bits >> i & 1)
