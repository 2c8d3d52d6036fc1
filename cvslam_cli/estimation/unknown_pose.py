"""Localising a vehicle whose initial pose is unknown (`fuse.initial.unknown`; extension
beyond the paper), in the shared map and, with `--prior-map`, in the prior map too.

Each frame of the vehicle, until it is localised:
1. its stereo matches are paired by descriptor with the landmarks of the state and, with a
   prior map, the prior's landmarks not in the state (`PriorLandmarks.archived`), and its
   pose found by PnP inside RANSAC (`localise.py`);
2. the position found must lie inside the vehicle's prior (chi-square, 3 dof,
   `localise_prior_chi2`);
3. with a prior map, against false localisation in a map of another place, the same pose
   must be found in `localise_confirm_frames` consecutive frames: the offset between the
   pose found and the vehicle's dead-reckoned prior must repeat within
   `CONFIRM_RANGE_FRACTION` of the inliers' median range and `CONFIRM_YAW_RAD` (dead
   reckoning drifts by centimetres between frames, and a PnP pose on a map known to metres
   scatters by a few per cent of the range; a chance fit to look-alikes does not land on the
   same offset twice). In the shared map, which this run's own vehicles made, one frame is
   enough;
4. the inlier prior landmarks are inserted (as many as fit, `PriorLandmarks.reinsert`), the
   vehicle is relinearised at the pose found (its covariance, the broad prior, is kept) and
   updated with every inlier in the state: from then on it is an ordinary vehicle. What the
   prior does not know (`fuse.initial.unknown`: position and heading) is taken from the pose
   found, roll and pitch stay the state's: they are known as at any start (and from gravity
   with an IMU), and a camera looking down trades tilt for position over a small patch of
   map (PnP's pitch 1-2 degrees off, its position metres off, on the prior-map test's
   scene; BENCHMARKS.md "Fuse: 60 landmarks a frame for a team with IMUs").
The localisation (and the prior landmarks brought in) are logged as events.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cvslam_cli.estimation.association import TYPE_2, classify, record_observations, unassociated
from cvslam_cli.estimation.events import EventLog
from cvslam_cli.estimation.frame import FrameMatches, FrameOutcome
from cvslam_cli.estimation.localise import Localisation, localise
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.new_landmarks import NewLandmarks
from cvslam_cli.estimation.prior_map import PriorLandmarks
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.update import VisualUpdater
from cvslam_cli.estimation.vehicle import VehiclePose, VehicleRun
from cvslam_cli.records.arrays import F64, I64

CONFIRM_RANGE_FRACTION = 0.05
"""Two localisations of consecutive frames agree when the offsets of their poses from the
vehicle's dead-reckoned prior differ by less than this fraction of the median range from
the camera to the inlier landmarks (m / m) ..."""
CONFIRM_YAW_RAD = float(np.radians(3.0))
"""... and their heading offsets by less than this (rad)."""


@dataclass(frozen=True)
class _Pending:
    """A localisation waiting for confirmation: the offset of the pose found from the
    vehicle's prior (position (3,), heading) and in how many consecutive frames it held."""

    dp_m: F64
    dyaw_rad: float
    frames: int


class UnknownPoseLocaliser:
    """Localising the vehicles of `runs` whose pose is unknown (module docstring) in the
    landmarks of `state` and, when `prior` is given, the prior map's; `bounded` gives the
    vehicles NH-infinity's bound is on (`Cooperation.bounded_vehicles`), `mapper` makes room
    for prior landmarks."""

    def __init__(
        self,
        state: JointState,
        book: LandmarkBook,
        runs: list[VehicleRun],
        updater: VisualUpdater,
        events: EventLog,
        settings: SlamSettings,
        bounded: Callable[[], list[str]],
        mapper: NewLandmarks,
        prior: PriorLandmarks | None,
    ) -> None:
        self.state = state
        self.book = book
        self.runs = runs
        self.updater = updater
        self.events = events
        self.settings = settings
        self.bounded = bounded
        self.mapper = mapper
        self.prior = prior
        self.confirm_frames = settings.localise_confirm_frames if prior is not None else 1
        self.names = [r.vin.name for r in runs]
        self._pending: dict[str, _Pending] = {}

    def localise_vehicle(self, run: VehicleRun, frame: FrameMatches) -> FrameOutcome:
        """Try to localise run's vehicle from this frame; on the confirming frame, move it
        to the pose found and update it with the inliers (module docstring, steps 1-4)."""
        s, st, book, vin = self.settings, self.state, self.book, run.vin
        n = len(frame)
        out = FrameOutcome(unassociated(n).type)
        state_ids = book.slot_ids.copy()
        prior_ids = (
            self.prior.archived(frame.stamp_ns)
            if self.prior is not None
            else np.zeros(0, dtype=np.int64)
        )
        ids = np.concatenate([state_ids, prior_ids])
        if len(ids) < s.localise_min_inliers or n < s.localise_min_inliers:
            return out
        m = np.concatenate([st.landmarks().reshape(-1, 3), book.p_nav_m[prior_ids]])
        found = localise(
            vin.obs, frame.z, frame.desc, m, book.desc[ids], ratio=s.descriptor_ratio,
            max_descriptor_distance=s.max_descriptor_distance,
            reprojection_px=s.localise_reprojection_px, min_inliers=s.localise_min_inliers,
            seed=len(run.stamps_ns),
        )  # fmt: skip
        prior = VehiclePose.of(st, vin)
        if found is None:
            self._pending.pop(vin.name, None)
            return out
        d = found.p_nav_m - prior.p_nav_m
        if float(d @ np.linalg.solve(prior.cov[:3, :3], d)) > s.localise_prior_chi2:
            self._pending.pop(vin.name, None)
            out.rejected = len(found.match_rows)
            return out
        # angles continuous with the state's (which are not wrapped)
        e0 = prior.euler_rad
        euler = e0 + (found.euler_rad - e0 + np.pi) % (2 * np.pi) - np.pi
        ranges = np.linalg.norm(m[found.landmark_rows] - found.p_nav_m, axis=1)
        tol_m = CONFIRM_RANGE_FRACTION * float(np.median(ranges))
        if not self._confirmed(vin.name, d, float(euler[2] - e0[2]), tol_m):
            return out
        return self._accept(run, frame, found, ids[found.landmark_rows], euler, d, len(state_ids))

    def _confirmed(self, name: str, dp_m: F64, dyaw_rad: float, tol_m: float) -> bool:
        """Whether this frame's offset confirms the previous frames' to `tol_m` (module
        docstring, step 3)."""
        last = self._pending.get(name)
        agrees = (
            last is not None
            and float(np.linalg.norm(dp_m - last.dp_m)) < tol_m
            and abs(dyaw_rad - last.dyaw_rad) < CONFIRM_YAW_RAD
        )
        frames = last.frames + 1 if agrees and last is not None else 1
        self._pending[name] = _Pending(dp_m, dyaw_rad, frames)
        return frames >= self.confirm_frames

    def _accept(
        self,
        run: VehicleRun,
        frame: FrameMatches,
        found: Localisation,
        ids: I64,
        euler: F64,
        d: F64,
        n_state: int,
    ) -> FrameOutcome:
        """The vehicle moved to the pose found, the inlier prior landmarks (ids at or past
        `n_state` of the candidates) inserted as many as fit, and one update with every
        inlier in the state (module docstring, step 4)."""
        s, st, book, vin = self.settings, self.state, self.book, run.vin
        self._pending.pop(vin.name, None)
        prior = VehiclePose.of(st, vin)
        # what the prior does not know (position, heading) from the pose found; roll and
        # pitch stay the state's (module docstring, step 4)
        euler = np.array([prior.euler_rad[0], prior.euler_rad[1], euler[2]])
        st.x[prior.index] = vin.model.with_pose(prior.x, found.p_nav_m, euler)
        st.reset_gauge(vin.name)
        from_prior = found.landmark_rows >= n_state
        if self.prior is not None:
            protected = np.flatnonzero(np.isin(book.slot_ids, ids[~from_prior]))
            room = self.mapper.make_room(run, self.runs, protected, np.flatnonzero(from_prior))
            if len(room):
                self.prior.reinsert(run, ids[room])
                self.events.add(frame.stamp_ns, "prior_map", vin.name, "", len(room))
        # the inliers in the state now (an inlier that did not fit is left out)
        slot_of = {int(i): k for k, i in enumerate(book.slot_ids)}
        keep = np.array([int(i) in slot_of for i in ids], dtype=bool)
        slots = np.array([slot_of[int(i)] for i in ids[keep]], dtype=np.int64)
        match_rows = found.match_rows[keep]
        k = len(slots)
        pose = VehiclePose.of(st, vin)  # relinearised
        pred, _ = self.updater.predict(vin, pose, slots)
        res = self.updater.update(
            pose.index, pred, np.arange(k), frame.z[match_rows], self.bounded()
        )
        ids_used = book.slot_ids[slots]
        types = classify(
            np.zeros(len(frame), dtype=bool), match_rows, book.last_seen_ns[ids_used, run.index],
            frame.stamp_ns, s.loop_closure_gap_ns,
        )  # fmt: skip
        out = FrameOutcome(
            types.type, slots, type2=types.count(TYPE_2), nis=res.nis, dof=4 * k, gamma=res.gamma,
            gamma_raised=res.gamma_raised,
        )  # fmt: skip
        others = book.other_observers(ids_used, run.index, self.names)
        record_observations(st, book, run, slots, frame.stamp_ns, frame.z[match_rows])
        run.localised_ns = frame.stamp_ns
        self.events.add(
            frame.stamp_ns, "localisation", vin.name, others, k, None,
            self._message(frame, found, run, ids_used, d),
        )  # fmt: skip
        return out

    def _message(
        self, frame: FrameMatches, found: Localisation, run: VehicleRun, ids_used: I64, d: F64
    ) -> str:
        """The localisation event's text: when, on what, and how far the vehicle moved."""
        after_s = (frame.stamp_ns - run.vin.start_ns) * 1e-9
        where, pairs = "", "descriptor pairs"
        if self.prior is not None:
            n_prior = int(np.sum(ids_used < self.prior.prior.n))
            where = " in the prior map"
            pairs += (
                f" ({n_prior} prior-map landmarks), the same pose in {self.confirm_frames} "
                "consecutive frames"
            )
        return (
            f"localised{where} {after_s:.2f} s after its start: PnP on {len(found.match_rows)} "
            f"of {found.candidates} {pairs}, reprojection RMS {found.rms_px:.2f} px, moved "
            f"{np.linalg.norm(d):.1f} m from its prior"
        )
