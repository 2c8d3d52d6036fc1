"""Stereo VSLAM with one central filter over one or several vehicles (paper sections "Single
visual SLAM", "Nonlinear H-infinity filter", "Cooperative VSLAM"). Pure numpy: the inputs
are arrays (motion samples, feature sets), the outputs arrays and row records; the `fuse`
stage does the I/O.

Every vehicle's camera frames are processed in timestamp order over all vehicles, as a
ground station would. A frame of vehicle v at time t (`Slam._frame`) is six steps:

1. predict (eq. 1-2): v's motion model is run from its last time to t over its motion
   samples (IMU or odometry, each piece driven by the samples at its midpoint,
   `motion_segments`; one step for the constant-velocity model) and the joint covariance
   propagated on v's block only (`JointState.predict`), with NH-infinity's scaled process
   noise (eq. 13);
2. associate and classify: the landmarks in view are predicted into both images with their
   innovation covariances and matched to the frame's stereo matches (`association.py`);
   evicted landmarks that the unclaimed matches re-observe are brought back into the state
   first (`reactivation.py`: a loop closure on ground whose landmarks left the state);
   the accepted ones (at most `max_updates_per_frame`, `update_budget.py`, spread over the
   image, the longest-unseen first) are classified into the paper's types 1 and 2
   (`association.classify`). A vehicle whose pose is not known yet is localised in the
   shared map instead (`unknown_pose.py`); before that, the frame may be located in the map
   by appearance, and a vehicle whose pose that contradicts is lost and found again
   (`relocalisation.py`);
3. update: one stacked EKF or NH-infinity update with those observations (eq. 19,
   `update.py`, `filters.py`) and the window's pending rows (step 5 of the frame before),
   iterated when the vehicle is too uncertain for one linearisation (`linearisation.py`);
   loop closures and cross-vehicle observations are logged (`events.py`);
4. map: when fewer than `target_tracked` landmarks were updated, confirmed type-3 matches
   become landmarks, the state kept under its landmark bound by eviction
   (`new_landmarks.py`, `mapping.py`), and other vehicles' simultaneous observations of
   them are used at once (joint initialisation, `cooperation.py`);
5. window (when `fuse.window.clones` > 0): the pose is cloned and the frame's remaining
   points continue or start feature tracks; the rows of the tracks that end wait for the
   next update (`window_update.py`, `tracks.py`: the MSCKF's use of the points never
   mapped);
6. record: pose and its covariance, one timeline row, and the divergence check (`events.py`);
   with a window, the poses of the clones that left it replace their frames' records (the
   window's last estimate of them: a fixed-lag smoother's output, `Slam._revise`).

A run started from a prior map (`prior_map.py`) has the prior's landmarks in its book from
the start, out of the state: step 2 brings them in as it brings back evicted landmarks, and
a vehicle whose pose is unknown is localised in them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cvslam_cli.estimation.association import (
    TYPE_1,
    TYPE_2,
    TYPE_3,
    FeatureTypes,
    LandmarkPrediction,
    absence_ns,
    associate,
    classify,
    descriptor_tests,
    lookalike_gates,
    noise_scale,
    pose_consistent,
    record_observations,
    spread_order,
    unassociated,
    visible_slots,
)
from cvslam_cli.estimation.cooperation import Cooperation
from cvslam_cli.estimation.events import Divergence, DivergenceMonitor, EventLog
from cvslam_cli.estimation.frame import FrameMatches, FrameOutcome
from cvslam_cli.estimation.gauge import constrained
from cvslam_cli.estimation.landmark_coordinates import coordinates, resolve
from cvslam_cli.estimation.linearisation import bearings_too_uncertain, too_uncertain
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.motion.calibration import right_cx_row
from cvslam_cli.estimation.motion.models import propagate
from cvslam_cli.estimation.motion.segments import motion_segments
from cvslam_cli.estimation.new_landmarks import NewLandmarks
from cvslam_cli.estimation.octave_noise import OctaveBearingNoise, match_octaves
from cvslam_cli.estimation.octave_noise import resolve as resolve_octaves
from cvslam_cli.estimation.prior_map import OFFSET_BLOCK, PriorLandmarks, PriorMap
from cvslam_cli.estimation.reactivation import Reactivation
from cvslam_cli.estimation.relocalisation import (
    Contradiction,
    PlaceRecognition,
    forget_mapped,
    lost_variances,
)
from cvslam_cli.estimation.settings import SlamSettings, landmark_bound
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.unknown_pose import UnknownPoseLocaliser
from cvslam_cli.estimation.update import VisualUpdater
from cvslam_cli.estimation.update_budget import resolve as resolve_budget
from cvslam_cli.estimation.vehicle import VehicleInput, VehiclePose, VehicleRun
from cvslam_cli.estimation.window_update import LaggedPose, SlidingWindow
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.landmark_archive import LandmarkArchive, merge_archives
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.observations import ObservationTable


@dataclass(frozen=True, eq=False)
class VehicleTrack:
    """Estimates at the vehicle's processed frames: stamps_ns (F,), x (F, n) vehicle states,
    p_nav_m (F, 3), euler_rad (F, 3), pose_cov (F, 6, 6) of (p, Psi)."""

    name: str
    stamps_ns: I64
    x: F64
    p_nav_m: F64
    euler_rad: F64
    pose_cov: F64


@dataclass(frozen=True, eq=False)
class SlamResult:
    tracks: dict[str, VehicleTrack]
    timeline: list[dict[str, Any]]
    events: list[dict[str, Any]]
    archive: LandmarkArchive
    divergence: Divergence | None
    gamma_raised: int
    # every landmark observation used, ids as in `landmarks` (fuse/observations.npz, refine)
    observations: ObservationTable | None = None
    # with a prior map: its common offset b (3,) as estimated at the end, and its covariance
    prior_offset_m: F64 | None = None
    prior_offset_cov_m2: F64 | None = None
    # vehicles whose rig's right principal point was estimated: (its estimate, std) px at the
    # end (a state of its block, motion/calibration.py; rig_calibration.py)
    right_cx_px: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def landmarks(self) -> LandmarkMap:
        """The map's summary (map.csv, map.ply)."""
        return self.archive.landmark_map()


@dataclass(frozen=True, eq=False)
class _Associated:
    """A frame's accepted associations, in update order: `pred` the landmarks in view
    predicted, `pred_rows` / `match_rows` (k,) the pairs used, `types` the frame's feature
    types."""

    pred: LandmarkPrediction
    pred_rows: I64
    match_rows: I64
    types: FeatureTypes


class Slam:
    """The central filter over `vehicles` (module docstring)."""

    def __init__(
        self,
        vehicles: list[VehicleInput],
        settings: SlamSettings,
        progress: Callable[[int], None] | None = None,
        prior: LandmarkArchive | None = None,
    ) -> None:
        self.settings = settings
        self.vehicles = vehicles
        self.names = [v.name for v in vehicles]
        # a map from an earlier run (prior_map.py): its common offset is a block of the state
        self.prior = None if prior is None else PriorMap(prior, settings)
        kinds = [v.model.kind for v in vehicles]
        self.state = JointState(
            [(v.name, v.model, v.x0, v.P0) for v in vehicles]
            + ([self.prior.offset_block()] if self.prior is not None else []),
            coordinates(resolve(settings.landmark_coordinates, kinds)[0]),
            gauge=constrained(settings.observability_constrained, kinds, self.prior is not None)[0],
        )
        self.book = LandmarkBook(len(vehicles))
        self.runs = [VehicleRun.start(v, i) for i, v in enumerate(vehicles)]
        # the landmarks each frame updates and keeps tracked
        self.budget = resolve_budget(
            settings.max_updates_per_frame, settings.target_tracked, kinds
        )[0]
        self.updater = VisualUpdater(self.state, settings.filter, settings.pixel_sigma_px)
        self.octaves = OctaveBearingNoise.of(
            resolve_octaves(settings.octave_bearing_variance, kinds)[0],
            [match_octaves(v.features) for v in vehicles],
        )
        self.events = EventLog(settings.event_merge_ns)
        self.cooperation = Cooperation(
            self.state, self.book, self.runs, self.updater, self.events, settings
        )
        # the bound on landmarks in the state grows with the vehicles sharing it
        self.mapper = NewLandmarks(
            self.state, self.book, settings, landmark_bound(settings, len(vehicles))
        )
        self.window = (
            SlidingWindow(
                self.state, settings.window, settings.filter, self.updater.gamma,
                self.updater.R_pixel,
            )
            if settings.window.window > 0
            else None
        )  # fmt: skip
        self.reactivation = Reactivation(self.state, self.book, settings, self.updater.R_pixel_hat)
        self.prior_landmarks: PriorLandmarks | None = None
        if self.prior is not None:
            self.prior.seed(self.book)
            self.prior_landmarks = PriorLandmarks(
                self.state, self.book, settings, self.updater.R_pixel_hat, self.prior
            )
        self.localiser = UnknownPoseLocaliser(
            self.state, self.book, self.runs, self.updater, self.events, settings,
            self.cooperation.bounded_vehicles, self.mapper, self.prior_landmarks,
            self.reactivation,
        )  # fmt: skip
        self.recognition = PlaceRecognition(
            self.state, self.book, settings, self.updater.R_pixel_hat
        )
        self.monitor = DivergenceMonitor(self.names, settings.nis_window, settings.nis_per_dof_max)
        self.timeline: list[dict[str, Any]] = []
        self.divergence: Divergence | None = None
        self.progress = progress

    def _schedule(self) -> list[tuple[int, int, int]]:
        """(stamp, vehicle index, frame index) of every frame at or after the vehicle's
        start, in time order (ties: vehicle order)."""
        items = []
        for i, v in enumerate(self.vehicles):
            st = v.features.frame_stamp_ns
            for f in np.flatnonzero(st >= v.start_ns):
                items.append((int(st[f]), i, int(f)))
        items.sort()
        return items

    def run(self) -> SlamResult:
        for stamp, vi, f in self._schedule():
            self._frame(self.runs[vi], stamp, f)
            if self.progress is not None:
                self.progress(1)
            if self.divergence is not None:
                break
        if self.divergence is None:
            self._flush_window()
        return self._result()

    # ------------------------------------------------------------------ one frame
    def _frame(self, run: VehicleRun, t_ns: int, f: int) -> None:
        """One frame of run's vehicle: the six steps of the module docstring."""
        t_start = time.perf_counter()
        self._predict(run, t_ns)
        frame = FrameMatches.of(
            run.vin.features, f, t_ns, self.settings.max_new_depth_sigma_ratio,
            VehiclePose.of(self.state, run.vin).right_cx_shift(),
        )  # fmt: skip
        # the map by appearance against the filter's pose: a vehicle it contradicts is lost
        contradiction = self.recognition.check(run, frame) if run.localised else None
        recognised = None
        if contradiction is not None and not contradiction.lost:
            recognised, contradiction = contradiction, None
        if contradiction is not None and not self._lose(run, t_ns, contradiction.why):
            contradiction = None  # diverged instead
        localising = not run.localised
        found = None
        if localising:  # pose unknown: localise in the map (an update of its own)
            out = self._localise(run, frame, contradiction)
        elif recognised is not None:  # too uncertain for its windows: found by appearance
            out = self.localiser.relocalise(
                run, frame, recognised.found, recognised.ids, weight=recognised.weight
            )
            localising = True
        else:
            found, out = self._associate(run, frame)
            reactivated = self._reactivate(run, frame, out)
            if reactivated:  # associate again, with the landmarks brought back
                found, out = self._associate(run, frame)
                out.reactivated = reactivated
            if found is not None:
                self._update(run, frame, found, out)
        out.lost = contradiction is not None
        if found is None or localising:  # the window's pending rows, alone
            self._flush_window()
        # landmark uncertainty of this frame's updated landmarks (before any eviction)
        lm_std = self._landmark_sigma(out.updated_slots)
        prior_used = self.prior.count(self.book, out.updated_slots) if self.prior else 0
        if not localising:
            self.recognition.tracked(
                run, t_ns, out.visible, len(out.updated_slots), self.budget.max_updates
            )
            self._map(run, frame, out)
            self._window(run, frame, out)
        self._next_candidates(run, frame, out)
        self._record(run, frame, out, lm_std, t_start, prior_used)
        if self.window is not None:
            self._revise(self.window.take_lagged())

    def _localise(
        self, run: VehicleRun, frame: FrameMatches, contradiction: Contradiction | None
    ) -> FrameOutcome:
        """Step 2 for a vehicle whose pose is unknown: localised at once where the map by
        appearance put it when that is what just lost it (the check's inliers still in the
        map, if enough), else by searching the map (`unknown_pose.py`)."""
        if contradiction is not None:
            c = contradiction.without_forgotten(self.book)
            if len(c.ids) >= self.settings.localise_min_inliers:
                return self.localiser.relocalise(run, frame, c.found, c.ids)
        return self.localiser.localise_vehicle(run, frame)

    def _predict(self, run: VehicleRun, t_ns: int) -> None:
        """Step 1 (eq. 1-2, 13)."""
        vin = run.vin
        U, dts = motion_segments(vin.motion_stamps_ns, vin.motion_inputs, run.t_ns, t_ns)
        if len(dts):
            x_v = self.state.vehicle_x(vin.name).copy()
            x_new, F, Q = propagate(vin.model, x_v, U, dts)
            self.state.predict(vin.name, x_new, F, self.settings.filter.process_noise(Q))
        run.t_ns = t_ns

    def _associate(
        self, run: VehicleRun, frame: FrameMatches
    ) -> tuple[_Associated | None, FrameOutcome]:
        """Step 2: the frame's matches associated with the landmarks in view (gate,
        descriptor test, one consistent vehicle correction), the ones to update with chosen
        and every match classified."""
        s = self.settings
        pose = VehiclePose.of(self.state, run.vin)
        visible = visible_slots(
            self.state, self.book, run, pose, s.max_view_angle_rad,
            s.other_vehicle_max_distance_ratio,
        )  # fmt: skip
        out = FrameOutcome(unassociated(len(frame)).type, visible=len(visible))
        if not (len(visible) and len(frame)):
            return None, out
        book = self.book
        ids_vis = book.slot_ids[visible]
        scale = noise_scale(book, ids_vis, run.index, s.other_vehicle_noise_ratio)
        pred, errors = self.updater.predict(pose, visible, scale)
        ratio, frame_wide = descriptor_tests(
            book, ids_vis, run.index, s.descriptor_ratio, s.other_vehicle_descriptor_ratio,
            s.other_vehicle_ratio_over_frame,
        )  # fmt: skip
        gates = lookalike_gates(
            book, ids_vis, run.index, pred.S, s.gate_chi2, s.other_vehicle_lookalike_bound
        )
        assoc = associate(
            pred, book.desc[ids_vis], frame.z, frame.desc, s.gate_chi2, ratio,
            s.max_descriptor_distance, frame_wide, gates,
        )  # fmt: skip
        ok = pose_consistent(
            pred, assoc.pred_index, frame.z[assoc.match_index], pose.P_vv,
            errors, self.updater.R_pixel_hat, s.consistency_chi2,
        )  # fmt: skip
        out.rejected = int(np.sum(~ok))
        if not ok.any():
            out.types = classify(assoc.near_landmark).type
            return None, out
        # the longest-unseen first, spread over the image, at most the budget's
        last_seen = book.last_seen_ns[ids_vis[assoc.pred_index[ok]], run.index]
        absent_ns = absence_ns(last_seen, frame.stamp_ns)
        order = spread_order(
            frame.z[assoc.match_index[ok], :2], -absent_ns.astype(float),
            tuple(run.vin.features.rig.size_px[0]),
        )[: self.budget.max_updates]  # fmt: skip
        pred_rows = assoc.pred_index[ok][order]
        match_rows = assoc.match_index[ok][order]
        types = classify(
            assoc.near_landmark, match_rows, last_seen[order], frame.stamp_ns,
            s.loop_closure_gap_ns,
        )  # fmt: skip
        out.types = types.type
        return _Associated(pred, pred_rows, match_rows, types), out

    def _reactivate(self, run: VehicleRun, frame: FrameMatches, out: FrameOutcome) -> int:
        """Step 2b: evicted landmarks that the frame's free matches re-observe brought back
        into the state (`reactivation.py`), then the prior map's (`prior_map.py`), logged;
        returns how many."""
        free = out.types == TYPE_3
        n = self._bring_back(self.reactivation, "reactivation", run, frame, free)
        if self.prior_landmarks is not None:
            n += self._bring_back(self.prior_landmarks, "prior_map", run, frame, free)
        return n

    def _bring_back(
        self, finder: Reactivation, kind: str, run: VehicleRun, frame: FrameMatches, free: Any
    ) -> int:
        """The landmarks out of the state that `finder` finds among the `free` matches (M,)
        brought in (as many as fit), logged as `kind` events; their matches no longer free."""
        if not finder.enabled:
            return 0
        found = finder.find(run, frame, free)
        if not len(found.ids):
            return 0
        pose = VehiclePose.of(self.state, run.vin)
        s = self.settings
        protected = visible_slots(
            self.state, self.book, run, pose, s.max_view_angle_rad,
            s.other_vehicle_max_distance_ratio,
        )  # fmt: skip
        room = self.mapper.make_room(run, self.runs, protected, np.arange(len(found.ids)))
        if not len(room):
            return 0
        ids = found.ids[room]
        finder.reinsert(run, ids)
        free[found.match_rows[room]] = False
        others = self.book.other_observers(ids, run.index, self.names)
        self.events.add(frame.stamp_ns, kind, run.vin.name, others, len(ids), found.absent_ns[room])
        return len(ids)

    def _update(
        self, run: VehicleRun, frame: FrameMatches, found: _Associated, out: FrameOutcome
    ) -> None:
        """Step 3: the stacked update (eq. 19) with the associated observations; loop
        closures and cross-vehicle observations logged."""
        s = self.settings
        vin = run.vin
        v_idx = self.state.vehicles[vin.name].index
        extra = self.window.pending_rows() if self.window is not None else None
        args = (
            found.pred, found.pred_rows, frame.z[found.match_rows],
            self.cooperation.bounded_vehicles(), extra,
        )  # fmt: skip
        bearing = (
            None if self.octaves is None else self.octaves.scale(frame.octave[found.match_rows])
        )
        if self._too_uncertain(run, frame, found):
            res, out.linearisations = self.updater.iterated_update(
                vin, *args, iterations=s.max_update_iterations, bearing_scale=bearing
            )
        else:
            res, out.linearisations = self.updater.update(v_idx, *args, bearing_scale=bearing), 1
        if self.window is not None:
            self.window.settle()
        k = len(found.pred_rows)
        types = found.types
        out.nis, out.dof = res.nis, 4 * k + (0 if extra is None else len(extra.r))
        out.gamma, out.gamma_raised = res.gamma, res.gamma_raised
        out.updated_slots = found.pred.slots[found.pred_rows]
        out.type1, out.type2 = types.count(TYPE_1), types.count(TYPE_2)
        loops = types.loop_closure
        out.loop = int(loops.sum())
        record_observations(
            self.state, self.book, run, out.updated_slots, frame.stamp_ns,
            frame.z[found.match_rows],
        )  # fmt: skip
        t_ns = frame.stamp_ns
        if out.loop >= s.loop_closure_min_landmarks:
            self.events.add(t_ns, "loop_closure", vin.name, "", out.loop, types.absent_ns[loops])
        first = types.type[found.match_rows] == TYPE_2
        ids = self.book.slot_ids[out.updated_slots[first]]
        others = self.book.other_observers(ids, run.index, self.names) if out.type2 else ""
        if others:  # none: the prior map's landmarks only (its `prior_map` events)
            self.events.add(
                t_ns, "cross_vehicle", vin.name, others, out.type2, types.absent_ns[first]
            )

    def _too_uncertain(self, run: VehicleRun, frame: FrameMatches, found: _Associated) -> bool:
        """Whether the frame's update is to be iterated (`linearisation.py`): the vehicle too
        uncertain for the frame's depths, or a landmark for its bearing."""
        s = self.settings
        pose_cov = VehiclePose.of(self.state, run.vin).cov[:3, :3]
        if too_uncertain(pose_cov, frame.p_cam_m, s.iterate_sigma_ratio):
            return True
        if s.iterate_bearing_sigma_rad <= 0:  # off (the default): no per-frame work
            return False
        S_left = found.pred.S[found.pred_rows][:, :2, :2]
        scale = found.pred.noise_scale
        R_left = self.updater.R_pixel_hat[:2, :2]
        if scale is not None:  # each observation's own noise (`association.noise_scale`)
            R_left = R_left * scale[found.pred_rows][:, None, None]
        fx_px = float(run.vin.features.rig.K[0][0, 0])
        return bearings_too_uncertain(S_left, R_left, fx_px, s.iterate_bearing_sigma_rad)

    def _landmark_sigma(self, slots: I64) -> float:
        """RMS standard deviation (m) of the landmarks in `slots` (nan for none)."""
        if not len(slots):
            return float("nan")
        lm_cov = self.state.landmark_covariances(slots)
        return float(np.sqrt(np.mean(np.trace(lm_cov, axis1=1, axis2=2))))

    def _map(self, run: VehicleRun, frame: FrameMatches, out: FrameOutcome) -> None:
        """Step 4: new landmarks (type 3) from the confirmed candidates, with joint
        initialisation (none while, or in the frame where, the vehicle is localised)."""
        want = self.mapper.wanted(len(out.updated_slots), self.budget.target_tracked)
        if not want:  # confirming costs an association: only when wanted
            return
        confirmed, priority = self.mapper.confirm(run, frame, out.types == TYPE_3)
        if not len(confirmed):
            return
        slots, out.new_rows = self.mapper.add(
            run, self.runs, frame, confirmed, priority, out.updated_slots, want
        )
        if len(slots) and self.settings.joint_initialisation:
            self.cooperation.joint_initialisation(run, slots, frame.stamp_ns)
        out.type3 = len(slots)

    def _window(self, run: VehicleRun, frame: FrameMatches, out: FrameOutcome) -> None:
        """Step 5: clone the pose; the matches neither a landmark's observation nor a new
        landmark continue or start tracks; the tracks that end update the window."""
        if self.window is None:
            return
        free = out.types == TYPE_3
        free[out.new_rows] = False
        out.window = self.window.step(run.vin, frame, np.flatnonzero(free))

    def _revise(self, lagged: list[LaggedPose]) -> None:
        """Step 6's end: the poses of earlier frames as the window last estimated them, in
        place of what was recorded at the frame (a fixed-lag smoother's output; the timeline
        keeps the frame's own): the vehicle's state moved to that pose (`with_pose`, the
        motion it carries kept) and the pose covariance."""
        for lp in lagged:
            run = self.runs[self.names.index(lp.vehicle)]
            i = len(run.stamps_ns) - 1
            while run.stamps_ns[i] != lp.stamp_ns:
                i -= 1
            run.x[i] = run.vin.model.with_pose(run.x[i], lp.pose[:3], lp.pose[3:])
            run.pose_cov[i] = lp.cov

    def _flush_window(self) -> None:
        """The window's pending rows applied alone (a frame without a landmark update)."""
        if self.window is not None:
            self.window.flush(self.cooperation.bounded_vehicles())

    def _next_candidates(self, run: VehicleRun, frame: FrameMatches, out: FrameOutcome) -> None:
        """This frame's type-3 matches become the candidates the next frame may confirm
        (none while the vehicle's pose is unknown)."""
        if run.localised:
            self.mapper.remember_candidates(run, frame, out.types == TYPE_3)
        else:
            run.candidates = None

    def _record(
        self,
        run: VehicleRun,
        frame: FrameMatches,
        out: FrameOutcome,
        lm_std: float,
        t_start: float,
        prior_used: int = 0,
    ) -> None:
        """Step 6: the frame's estimate, timeline row and divergence check; `prior_used`:
        the prior map's landmarks among the updated."""
        st = self.state
        vin = run.vin
        pose = VehiclePose.of(st, vin)
        t_ns = frame.stamp_ns
        if not (np.all(np.isfinite(pose.x)) and np.all(np.isfinite(pose.P_vv))):
            self._diverge(vin.name, t_ns, "non-finite state or covariance")
        pose_cov = pose.cov
        p = pose.p_nav_m
        run.stamps_ns.append(t_ns)
        run.x.append(pose.x)  # a copy of the state's block
        run.pose_cov.append(pose_cov)
        reason = self.monitor.check(vin.name, out.nis, out.dof, out.visible, len(frame))
        if reason is not None and self.monitor.lost_map(vin.name):
            out.lost = self._lose(run, t_ns, reason)
        elif reason is not None:  # inconsistent, not lost: wrong settings, not bad luck
            self._diverge(vin.name, t_ns, reason)
        self.timeline.append(
            {
                "stamp_ns": t_ns,
                "vehicle": vin.name,
                "frame": frame.index,
                "state_size": st.n,
                "landmarks_in_state": st.n_landmarks,
                "landmarks_mapped": self.book.count,
                "matches": len(frame),
                "visible": out.visible,
                "rejected": out.rejected,
                "type1": out.type1,
                "type2": out.type2,
                "type3": out.type3,
                "loop_closure": out.loop,
                "reactivated": out.reactivated,
                "prior": prior_used,
                "localised": run.localised,
                "lost": out.lost,
                "sigma_pos_m": float(np.sqrt(np.trace(pose_cov[:3, :3]))),
                "sigma_att_rad": float(np.sqrt(np.trace(pose_cov[3:, 3:]))),
                "sigma_landmark_m": lm_std,
                "nis": out.nis,
                "nis_dof": out.dof,
                "gamma": out.gamma,
                "gamma_raised": out.gamma_raised,
                "linearisations": out.linearisations,
                "tracks_used": out.window.used,
                "tracks_rejected": out.window.rejected,
                "window_nis": out.window.nis,
                "window_nis_dof": out.window.dof,
                "x_m": float(p[0]),
                "y_m": float(p[1]),
                "z_m": float(p[2]),
                "ms": 1e3 * (time.perf_counter() - t_start),
            }
        )

    def _lose(self, run: VehicleRun, t_ns: int, why: str) -> bool:
        """Run's vehicle is lost (`relocalisation.py`: the map contradicted it, or it lost the
        map): it forgets its pose and is localised in the map again; a divergence instead
        (returns False) when relocalisation is off or the vehicle was lost `max_per_vehicle`
        times already."""
        s = self.settings.relocalisation
        name = run.vin.name
        if not s.enabled or run.losses >= s.max_per_vehicle:
            again = (
                f" (lost {run.losses} times before: fuse.relocalisation.max_per_vehicle)"
                if s.enabled
                else ""
            )
            self._diverge(name, t_ns, why + again)
            return False
        self._flush_window()
        rows, variances = lost_variances(run.vin.model, s)
        self.state.forget(name, rows, variances)
        forgotten = forget_mapped(
            self.state, self.book, run, t_ns, s.position_sigma_m**2, s.interval_ns
        )
        run.lose(t_ns)
        self.monitor.reset(name)
        self.events.add(t_ns, "lost", name, "", forgotten, None, why)
        return True

    def _diverge(self, vehicle: str, t_ns: int, reason: str) -> None:
        if self.divergence is None:
            self.divergence = Divergence(vehicle, t_ns, reason)
            self.events.add(t_ns, "divergence", vehicle, "", 0, None, reason)

    # ------------------------------------------------------------------ result
    def _result(self) -> SlamResult:
        st, book = self.state, self.book
        if self.window is not None:
            self._revise(self.window.take_lagged() + self.window.in_window())
        if st.n_landmarks:
            slots = np.arange(st.n_landmarks)
            book.store_estimates(slots, st.landmarks(), st.landmark_covariances(slots))
        archive = book.archive(self.names, st.coords.name)
        if self.prior is not None:
            archive = self.prior.merged_archive(archive)
        tracks = {r.vin.name: _track(r.vin, r.stamps_ns, r.x, r.pose_cov) for r in self.runs}
        b, B = None, None
        if self.prior is not None:
            rows = st.vehicles[OFFSET_BLOCK].index
            b, B = st.x[rows].copy(), st.P[np.ix_(rows, rows)].copy()
        right_cx = {}
        for vin in self.vehicles:
            row = right_cx_row(vin.model)
            if row is not None:
                i = st.vehicles[vin.name].index[row]
                right_cx[vin.name] = (float(st.x[i]), float(np.sqrt(st.P[i, i])))
        return SlamResult(
            tracks, self.timeline, self.events.rows, archive, self.divergence,
            self.updater.gamma.raised_count, _observations(self.runs), b, B, right_cx,
        )  # fmt: skip


def _observations(runs: list[VehicleRun]) -> ObservationTable:
    """Every vehicle's observation log as one table (vehicle indices in `runs`' order)."""
    names = [r.vin.name for r in runs]
    return ObservationTable.concatenate(
        names, [(i, *r.observations.arrays()) for i, r in enumerate(runs)]
    )


def _track(vin: VehicleInput, stamps_ns: list[int], xs: list[F64], covs: list[F64]) -> VehicleTrack:
    model = vin.model
    X = np.array(xs).reshape(-1, model.n)
    poses = [model.pose(x) for x in X]
    return VehicleTrack(
        vin.name,
        np.asarray(stamps_ns, dtype=np.int64),
        X,
        np.array([q[0] for q in poses]).reshape(-1, 3),
        np.array([q[1] for q in poses]).reshape(-1, 3),
        np.array(covs).reshape(-1, 6, 6),
    )


def dead_reckoning_track(vin: VehicleInput) -> VehicleTrack:
    """The same motion input without any correction, at the vehicle's frame stamps from its
    start (pose covariance: the motion model's own, growing)."""
    stamps = vin.features.frame_stamp_ns
    stamps = stamps[stamps >= vin.start_ns]
    x = vin.x0.copy()
    P = vin.P0.copy()
    t = vin.start_ns
    X, covs = [], []
    for s_ns in stamps:
        U, dts = motion_segments(vin.motion_stamps_ns, vin.motion_inputs, t, int(s_ns))
        if len(dts):
            x, F, Q = propagate(vin.model, x, U, dts)
            P = F @ P @ F.T + Q
        t = int(s_ns)
        J = vin.model.pose_jacobian(x)
        X.append(x.copy())
        covs.append(J @ P @ J.T)
    X_arr = np.array(X).reshape(-1, vin.model.n)
    poses = [vin.model.pose(xx) for xx in X_arr]
    return VehicleTrack(
        vin.name,
        stamps.astype(np.int64),
        X_arr,
        np.array([q[0] for q in poses]).reshape(-1, 3),
        np.array([q[1] for q in poses]).reshape(-1, 3),
        np.array(covs).reshape(-1, 6, 6),
    )


def merge_results(results: list[SlamResult]) -> SlamResult:
    """One result from vehicles run each in its own filter (`--single`): tracks side by side,
    timeline and events in time order, the maps concatenated with ids renumbered
    (`merge_archives`)."""
    divergences = [r.divergence for r in results if r.divergence is not None]
    offsets = np.cumsum([0] + [len(r.archive) for r in results])  # as merge_archives numbers
    return SlamResult(
        tracks={k: v for r in results for k, v in r.tracks.items()},
        timeline=sorted((row for r in results for row in r.timeline), key=lambda x: x["stamp_ns"]),
        events=sorted((e for r in results for e in r.events), key=lambda x: x["stamp_ns"]),
        archive=merge_archives([r.archive for r in results]),
        divergence=min(divergences, key=lambda d: d.stamp_ns) if divergences else None,
        gamma_raised=sum(r.gamma_raised for r in results),
        observations=_merged_observations(results, offsets),
    )


def _merged_observations(results: list[SlamResult], id_offsets: I64) -> ObservationTable | None:
    """The observation tables of runs merged by `merge_results` (landmark ids renumbered
    like the maps: run k's ids shifted by id_offsets[k])."""
    tables = [r.observations for r in results if r.observations is not None]
    if len(tables) < len(results):
        return None
    names = [n for t in tables for n in t.vehicles]
    parts, base = [], 0
    for t, off in zip(tables, id_offsets, strict=False):
        for i in range(len(t.vehicles)):
            sel = t.vehicle == i
            parts.append((base + i, t.stamp_ns[sel], t.landmark_id[sel] + off, t.z_px[sel]))
        base += len(t.vehicles)
    return ObservationTable.concatenate(names, parts)
