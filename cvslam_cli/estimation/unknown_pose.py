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

A vehicle lost during the run (`relocalisation.py`: the map by appearance contradicted its
pose, or it lost the map) is localised again the same way, among the evicted landmarks too
(brought back as re-activations), the same pose required in `localise_confirm_frames`
frames, its roll and pitch taken from the pose found as well (it forgot them); or at once
at the pose the check that lost it found (`relocalise`). Logged as `relocalisation`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cvslam_cli.estimation.association import TYPE_2, classify, record_observations, unassociated
from cvslam_cli.estimation.events import EventLog
from cvslam_cli.estimation.frame import FrameMatches, FrameOutcome
from cvslam_cli.estimation.localise import Localisation, PoseConfirmation, localise
from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.new_landmarks import NewLandmarks
from cvslam_cli.estimation.prior_map import PriorLandmarks
from cvslam_cli.estimation.reactivation import Reactivation
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.update import VisualUpdater
from cvslam_cli.estimation.vehicle import VehiclePose, VehicleRun
from cvslam_cli.records.arrays import F64, I64


class UnknownPoseLocaliser:
    """Localising the vehicles of `runs` whose pose is unknown (module docstring) in the
    landmarks of `state` and, when `prior` is given, the prior map's; a lost vehicle
    (`relocalisation.py`) among the evicted landmarks too, brought back by `reactivation`;
    `bounded` gives the vehicles NH-infinity's bound is on
    (`Cooperation.bounded_vehicles`), `mapper` makes room for landmarks brought in."""

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
        reactivation: Reactivation,
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
        self.reactivation = reactivation
        # in the shared map one frame is enough; in a prior map, or the whole map of a lost
        # vehicle, the same pose in several (module docstring, step 3)
        self._first = PoseConfirmation(settings.localise_confirm_frames if prior else 1)
        self._again = PoseConfirmation(settings.localise_confirm_frames)
        self.names = [r.vin.name for r in runs]

    def localise_vehicle(self, run: VehicleRun, frame: FrameMatches) -> FrameOutcome:
        """Try to localise run's vehicle from this frame; on the confirming frame, move it
        to the pose found and update it with the inliers (module docstring, steps 1-4)."""
        s, st, book, vin = self.settings, self.state, self.book, run.vin
        n = len(frame)
        out = FrameOutcome(unassociated(n).type)
        confirmation = self._again if run.lost_ns is not None else self._first
        none = np.zeros(0, dtype=np.int64)
        state_ids = book.slot_ids.copy()
        prior_ids = self.prior.archived(frame.stamp_ns) if self.prior is not None else none
        own_ids = self.reactivation.archived(frame.stamp_ns, 0) if run.lost_ns is not None else none
        ids = np.concatenate([state_ids, prior_ids, own_ids])
        if len(ids) < s.localise_min_inliers or n < s.localise_min_inliers:
            return out
        m = np.concatenate([st.landmarks().reshape(-1, 3), book.p_nav_m[ids[len(state_ids) :]]])
        found = localise(
            vin.obs, frame.z, frame.desc, m, book.desc[ids], ratio=s.descriptor_ratio,
            max_descriptor_distance=s.max_descriptor_distance,
            reprojection_px=s.localise_reprojection_px, min_inliers=s.localise_min_inliers,
            seed=len(run.stamps_ns), age=ids,
        )  # fmt: skip
        prior = VehiclePose.of(st, vin)
        if found is None:
            confirmation.drop(vin.name)
            return out
        d = found.p_nav_m - prior.p_nav_m
        if _prior_d2(d, prior.cov[:3, :3]) > s.localise_prior_chi2:
            confirmation.drop(vin.name)
            out.rejected = len(found.match_rows)
            return out
        # angles continuous with the state's (which are not wrapped)
        e0 = prior.euler_rad
        euler = e0 + (found.euler_rad - e0 + np.pi) % (2 * np.pi) - np.pi
        ranges = np.linalg.norm(m[found.landmark_rows] - found.p_nav_m, axis=1)
        tol_m = confirmation.tolerance_m(ranges)
        if not confirmation.confirmed(vin.name, d, float(euler[2] - e0[2]), tol_m):
            return out
        confirmation.drop(vin.name)
        return self._accept(run, frame, found, ids[found.landmark_rows], euler, d)

    def relocalise(
        self,
        run: VehicleRun,
        frame: FrameMatches,
        found: Localisation,
        ids: I64,
        weight: F64 | None = None,
    ) -> FrameOutcome:
        """Run's vehicle, just lost because the map by appearance contradicted its pose
        (`relocalisation.PlaceRecognition`), moved at once to the pose that map gave
        (`found`, confirmed over frames already; its inliers' book ids `ids`), as a
        confirmed localisation is (module docstring, step 4). With `weight` (6, 6; the
        check's `Contradiction.weight`): not lost but too uncertain for its windows
        (`relocalisation.py`), logged as a `recognition`. Such a vehicle keeps its pose and
        covariance, and the inliers update it as a frame's associations do (iterated: it is
        too uncertain for one linearisation), unless the pose found carries all there is
        (`DOMINANT_WEIGHT` in every direction of position and heading: after a long
        blackout, 58 m of standard deviation against a pose found to decimetres), where the
        vehicle is moved to it first, for the update's linearisation. Moved there while its
        own pose still counts, the vehicle took the pose found's whole error under a
        covariance only the update shrank (`ugv2_yard` alone, 0.2 m of standard deviation
        among nearby walls: BENCHMARKS.md, "Fuse: a pose found by appearance, weighed
        against the filter's")."""
        pose = VehiclePose.of(self.state, run.vin)
        e0 = pose.euler_rad
        euler = e0 + (found.euler_rad - e0 + np.pi) % (2 * np.pi) - np.pi
        d = found.p_nav_m - pose.p_nav_m
        keep = weight is not None and not pose_found_dominates(weight)
        return self._accept(run, frame, found, ids, euler, d, weight is not None, keep)

    def _sources(self, ids: I64) -> I64:
        """(k,) where each landmark of `ids` is: 0 in the state, 1 a prior-map landmark not
        observed in this run, 2 evicted."""
        book = self.book
        source = np.full(len(ids), 2, dtype=np.int64)
        if self.prior is not None:
            unseen = np.all(book.last_seen_ns[ids] == NEVER, axis=1)
            source[(ids < self.prior.prior.n) & unseen] = 1
        source[book.in_state_mask()[ids]] = 0
        return source

    def _accept(
        self,
        run: VehicleRun,
        frame: FrameMatches,
        found: Localisation,
        ids: I64,
        euler: F64,
        d: F64,
        uncertain: bool = False,
        keep: bool = False,
    ) -> FrameOutcome:
        """The vehicle moved to the pose found (unless it `keep`s its own: `relocalise`),
        the inliers (book ids `ids`) out of the state (the prior map's, or evicted) brought
        in as many as fit, and one update with every inlier in the state (module docstring,
        step 4; iterated for a vehicle that keeps its pose)."""
        s, st, book, vin = self.settings, self.state, self.book, run.vin
        source = self._sources(ids)
        prior = VehiclePose.of(st, vin)
        # what the prior does not know from the pose found: position and heading; roll and
        # pitch stay the state's (module docstring, step 4), except for a lost vehicle,
        # which forgot them too (relocalisation.lost_variances)
        if run.lost_ns is None:
            euler = np.array([prior.euler_rad[0], prior.euler_rad[1], euler[2]])
        if not keep:
            st.x[prior.index] = vin.model.with_pose(prior.x, found.p_nav_m, euler)
            st.reset_gauge(vin.name)
        outside = np.flatnonzero(source > 0)
        if len(outside):
            protected = np.flatnonzero(np.isin(book.slot_ids, ids[source == 0]))
            room = self.mapper.make_room(run, self.runs, protected, outside)
            for kind, k in (("prior_map", 1), ("reactivation", 2)):
                these = ids[room[source[room] == k]]
                if not len(these):
                    continue
                if k == 1:
                    assert self.prior is not None
                    self.prior.reinsert(run, these)
                else:
                    absent = frame.stamp_ns - book.last_seen_ns[these].max(axis=1)
                    self.reactivation.reinsert(run, these)
                others = book.other_observers(these, run.index, self.names) if k == 2 else ""
                self.events.add(
                    frame.stamp_ns, kind, vin.name, others, len(these), absent if k == 2 else None
                )
        # the inliers in the state now (an inlier that did not fit is left out)
        slot_of = {int(i): k for k, i in enumerate(book.slot_ids)}
        inside = np.array([int(i) in slot_of for i in ids], dtype=bool)
        slots = np.array([slot_of[int(i)] for i in ids[inside]], dtype=np.int64)
        match_rows = found.match_rows[inside]
        k = len(slots)
        pose = VehiclePose.of(st, vin)  # relinearised
        pred, _ = self.updater.predict(pose, slots)
        if keep:
            res, _ = self.updater.iterated_update(
                vin, pred, np.arange(k), frame.z[match_rows], self.bounded()
            )
        else:
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
        if uncertain:
            kind = "recognition"
            sigma_m = float(np.sqrt(np.linalg.eigvalsh(prior.cov[:3, :3])[-1]))
            dist_m = float(np.linalg.norm(d))
            message = (
                f"found by appearance at a position sigma of {sigma_m:.1f} m (too uncertain "
                f"for its windows): PnP on {len(found.match_rows)} of {found.candidates} "
                f"descriptor pairs, reprojection RMS {found.rms_px:.2f} px, "
                + (f"{dist_m:.1f} m from its own pose, kept" if keep else f"moved {dist_m:.1f} m")
            )
        else:
            kind = "localisation" if run.lost_ns is None else "relocalisation"
            message = self._message(frame, found, run, ids_used, d)
        run.localise(frame.stamp_ns)
        self.events.add(frame.stamp_ns, kind, vin.name, others, k, None, message)
        return out

    def _message(
        self, frame: FrameMatches, found: Localisation, run: VehicleRun, ids_used: I64, d: F64
    ) -> str:
        """The localisation event's text: when, on what, and how far the vehicle moved."""
        if run.lost_ns is None:
            when = f"{(frame.stamp_ns - run.vin.start_ns) * 1e-9:.2f} s after its start"
        else:
            when = f"{(frame.stamp_ns - run.lost_ns) * 1e-9:.2f} s after it was lost"
        where, pairs = "", "descriptor pairs"
        confirm = self._again.frames if run.lost_ns is not None else self._first.frames
        if self.prior is not None:
            n_prior = int(np.sum(ids_used < self.prior.prior.n))
            where = " in the prior map"
            pairs += f" ({n_prior} prior-map landmarks)"
        if confirm > 1:
            pairs += f", the same pose in {confirm} consecutive frames"
        verb = "localised" if run.lost_ns is None else "relocalised"
        return (
            f"{verb}{where} {when}: PnP on {len(found.match_rows)} of {found.candidates} "
            f"{pairs}, reprojection RMS {found.rms_px:.2f} px, moved "
            f"{np.linalg.norm(d):.1f} m from its prior"
        )


# A pose found by appearance replaces a vehicle's own for the update's linearisation where it
# carries all there is: its weight against the filter's pose, P (P + C)^-1, at least this in
# every direction of position and heading (the filter's variance 99x the pose found's);
# below, the vehicle's own pose counts and it is kept (`relocalise`).
DOMINANT_WEIGHT = 0.99


def pose_found_dominates(weight: F64) -> bool:
    """Whether a pose found with `weight` (6, 6: position, Euler angles) against the
    filter's carries all there is (`DOMINANT_WEIGHT`)."""
    rows = [0, 1, 2, 5]  # position and heading: what a pose found replaces (`_accept`)
    return bool(np.min(np.linalg.eigvals(weight[np.ix_(rows, rows)]).real) >= DOMINANT_WEIGHT)


def _prior_d2(d: F64, P: F64) -> float:
    """The Mahalanobis distance d^T P^-1 d of a found position from the prior's, over the
    axes the vehicle's state has (a ground robot's height is no state: its variance is 0,
    and the PnP pose's height says nothing of its state)."""
    k = np.diag(P) > 0
    return float(d[k] @ np.linalg.solve(P[np.ix_(k, k)], d[k]))
