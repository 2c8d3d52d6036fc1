"""Stereo VSLAM with one central filter over one or several vehicles (paper sections "Single
visual SLAM", "Nonlinear H-infinity filter", "Cooperative VSLAM"). Pure numpy: the inputs
are arrays (motion samples, feature sets), the outputs arrays and row records; the `fuse`
stage does the I/O.

Every vehicle's camera frames are processed in timestamp order over all vehicles, as a
ground station would. For a frame of vehicle v at time t:

1. predict: v's motion model is run from its last time to t over its motion samples (IMU or
   odometry, zero-order hold; one step for the constant-velocity model) and the joint
   covariance propagated on v's block only (`JointState.predict`);
2. associate: landmarks in the state are predicted into both images with their innovation
   covariances and matched to the frame's stereo matches (`association.py`); each match is
   type 1 (landmark seen before by v), type 2 (mapped by other vehicles only, first seen by
   v now) or, when unmatched and room is needed, type 3 (new);
3. update: the accepted observations (at most `max_updates_per_frame`, spread over the image,
   the longest-unseen first) in one stacked EKF or NH-infinity update (eq. 19 observations);
4. map: when fewer than `target_tracked` landmarks were updated, new ones are initialised
   from the frame's triangulated points with the inverse model and their covariance and
   cross-covariance from the pose (standard SLAM augmentation); the state is kept under
   `landmark_bound` by eviction (`mapping.py`);
5. record: pose and its covariance, one timeline row, events (loop closure: a type-1
   re-observation after more than `loop_closure_gap_s`; type 2; divergence).

Divergence: the normalised innovation squared per measurement (NIS / dof, 1 on average for a
consistent filter), its median over the vehicle's last `window` updates (robust to a single
bad frame); above
`nis_per_dof_max`, or any non-finite number in its state, the run stops and says when. The
chi-square gate keeps gross innovations out of the NIS, so a frame where landmarks are
predicted in view but none matches inside its window (the filter has lost its map) counts as
infinite NIS.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.association import (
    LandmarkPrediction,
    associate,
    camera_depths,
    in_view,
    pose_consistent,
    predict_landmarks,
    spread_order,
)
from cvslam_cli.estimation.filters import UpdateResult
from cvslam_cli.estimation.localise import localise
from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.motion_models import MotionModel, propagate
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.state import FilterSettings, JointState
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet
from cvslam_cli.records.landmarks import LandmarkMap


@dataclass(frozen=True, eq=False)
class VehicleInput:
    """One vehicle: its motion model, initial state x0 (n,) / P0 (n, n) at `start_ns`,
    motion samples `motion_stamps_ns` (K,) with inputs (K, input_size) (empty for the
    constant-velocity model), its features and stereo observation model. `pose_known` False:
    x0 is only a rough prior; the vehicle is localised in the shared map first
    (`localise.py`) and neither updates nor maps until then."""

    name: str
    model: MotionModel
    x0: F64
    P0: F64
    start_ns: int
    motion_stamps_ns: I64
    motion_inputs: F64
    features: FeatureSet
    obs: StereoObservationModel
    pose_known: bool = True


@dataclass(frozen=True)
class SlamSettings:
    filter: FilterSettings = field(default_factory=FilterSettings)
    pixel_sigma_px: float = 0.5
    gate_chi2: float = 18.47  # chi2 with 4 dof at 0.999
    consistency_chi2: float = 13.28  # chi2 with 4 dof at 0.99
    descriptor_ratio: float = 0.8
    max_descriptor_distance: float = 350.0
    max_landmarks: int = 150  # with one vehicle in the filter ...
    landmarks_per_added_vehicle: int = 100  # ... plus this many per other vehicle ...
    max_landmarks_total: int = 400  # ... up to this many in all
    max_updates_per_frame: int = 30
    target_tracked: int = 30
    max_new_per_frame: int = 15
    max_new_depth_sigma_ratio: float = 0.25
    loop_closure_gap_ns: int = 20_000_000_000
    loop_closure_min_landmarks: int = 3
    event_merge_ns: int = 5_000_000_000
    joint_init_window_ns: int = 200_000_000
    nis_window: int = 20
    nis_per_dof_max: float = 10.0
    max_view_angle_rad: float = 1.3963  # 80 degrees
    localise_min_inliers: int = 12
    localise_reprojection_px: float = 2.0
    localise_prior_chi2: float = 16.27  # chi2 with 3 dof at 0.999


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


@dataclass(frozen=True)
class Divergence:
    vehicle: str
    stamp_ns: int
    reason: str


@dataclass(frozen=True, eq=False)
class SlamResult:
    tracks: dict[str, VehicleTrack]
    timeline: list[dict[str, Any]]
    events: list[dict[str, Any]]
    landmarks: LandmarkMap
    divergence: Divergence | None
    gamma_raised: int


def landmark_bound(s: SlamSettings, n_vehicles: int) -> int:
    """Landmarks the state holds at most with n vehicles: `max_landmarks` for the first
    vehicle, `landmarks_per_added_vehicle` for each other, up to `max_landmarks_total`. Each
    vehicle needs room for the landmarks it tracks; the older map, kept for loop closures
    and re-observations, is shared (measured: 2 UAVs at 125 each are as accurate as at 150
    each, one UAV loses 12 % at 125; BENCHMARKS.md, "Fuse: cooperative")."""
    grown = s.max_landmarks + (n_vehicles - 1) * s.landmarks_per_added_vehicle
    return min(grown, max(s.max_landmarks_total, s.max_landmarks))


def motion_segments(stamps_ns: I64, inputs: F64, t0_ns: int, t1_ns: int) -> tuple[F64, F64]:
    """Inputs and durations (s) of the motion steps from t0 to t1: breakpoints at the
    samples in (t0, t1), each piece driven by the latest sample at or before its start
    (zero-order hold; the first sample before any). (U (k, d), dts (k,))."""
    if t1_ns <= t0_ns:
        return np.zeros((0, inputs.shape[1])), np.zeros(0)
    if len(stamps_ns) == 0:
        return np.zeros((1, inputs.shape[1])), np.array([(t1_ns - t0_ns) * 1e-9])
    lo = np.searchsorted(stamps_ns, t0_ns, side="right")
    hi = np.searchsorted(stamps_ns, t1_ns, side="left")
    knots = np.concatenate([[t0_ns], stamps_ns[lo:hi], [t1_ns]])
    src = np.maximum(np.arange(lo - 1, hi), 0)
    return inputs[src], np.diff(knots) * 1e-9


# a frame with at least this many landmarks predicted in view and none matched counts as an
# update with infinite NIS for divergence detection (the filter has lost its map)
MIN_VISIBLE_FOR_LOST = 10


@dataclass(frozen=True, eq=False)
class _Candidates:
    """A vehicle's unmatched stereo points of its last frame (k): nav positions m (k, 3) with
    covariances cov (k, 3, 3) from its pose then, descriptors (k, 128), the observations z
    (k, 4) and the frame's stamp."""

    m: F64
    cov: F64
    desc: NDArray[np.uint8]
    z: F64
    stamp_ns: int

    def without(self, rows: I64) -> _Candidates:
        keep = np.ones(len(self.m), dtype=bool)
        keep[rows] = False
        return _Candidates(
            self.m[keep], self.cov[keep], self.desc[keep], self.z[keep], self.stamp_ns
        )


@dataclass
class _FrameCounts:
    """What one frame did (the timeline row's counts). near, used: (M,) matches inside some
    landmark's window / used in the update."""

    near: NDArray[np.bool_]
    used: NDArray[np.bool_]
    updated_slots: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    type1: int = 0
    type2: int = 0
    type3: int = 0
    loop: int = 0
    rejected: int = 0
    nis: float = float("nan")
    dof: int = 0
    gamma: float = float("nan")
    gamma_raised: bool = False


class _VehicleRun:
    """Per-vehicle bookkeeping during a run."""

    def __init__(self, vin: VehicleInput, index: int) -> None:
        self.vin = vin
        self.index = index
        self.t_ns = vin.start_ns
        self.stamps: list[int] = []
        self.x: list[F64] = []
        self.pose_cov: list[F64] = []
        self.nis_recent: deque[float] = deque(maxlen=1)
        # when the vehicle's pose became known: its start, or when it was localised
        self.localised_ns: int | None = vin.start_ns if vin.pose_known else None
        # last frame's unmatched points, which the next frame may confirm
        self.candidates: _Candidates | None = None
        z = vin.features
        self.z_left = z.left_uv_px
        self.z_right = z.right_uv_px


class Slam:
    """The central filter over `vehicles` (module docstring)."""

    def __init__(
        self,
        vehicles: list[VehicleInput],
        settings: SlamSettings,
        progress: Callable[[int], None] | None = None,
    ) -> None:
        self.settings = settings
        self.vehicles = vehicles
        self.names = [v.name for v in vehicles]
        self.state = JointState([(v.name, v.model, v.x0, v.P0) for v in vehicles])
        self.book = LandmarkBook(len(vehicles))
        # the bound on landmarks in the state grows with the vehicles sharing it
        self.max_landmarks = landmark_bound(settings, len(vehicles))
        self.runs = {v.name: _VehicleRun(v, i) for i, v in enumerate(vehicles)}
        for r in self.runs.values():
            r.nis_recent = deque(maxlen=settings.nis_window)
        self.timeline: list[dict[str, Any]] = []
        self.events: list[dict[str, Any]] = []
        self._open_events: dict[tuple[str, str, str], dict[str, Any]] = {}
        self.divergence: Divergence | None = None
        self.gamma_raised = 0
        self.progress = progress

    # ------------------------------------------------------------------ schedule
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
            run = self.runs[self.names[vi]]
            self._frame(run, stamp, f)
            if self.progress is not None:
                self.progress(1)
            if self.divergence is not None:
                break
        return self._result()

    # ------------------------------------------------------------------ one frame
    def _predict(self, run: _VehicleRun, t_ns: int) -> None:
        vin = run.vin
        U, dts = motion_segments(vin.motion_stamps_ns, vin.motion_inputs, run.t_ns, t_ns)
        if len(dts):
            x_v = self.state.vehicle_x(vin.name).copy()
            x_new, F, Q = propagate(vin.model, x_v, U, dts)
            self.state.predict(vin.name, x_new, F, self.settings.filter.q_scale * Q)
        run.t_ns = t_ns

    def _visible(self, vin: VehicleInput, p: F64, euler: F64) -> I64:
        """Slots of the landmarks in the state predicted in front of the cameras, inside
        both images, and viewed from within the maximum angle of their viewing direction."""
        m_all = self.state.landmarks()
        slots = _in_view(vin, p, euler, m_all)
        views = _view_dirs(vin, p, euler, m_all[slots])
        return slots[self.book.seen_from(slots, views, np.cos(self.settings.max_view_angle_rad))]

    def _observe(self, run: _VehicleRun, slots: I64, stamp_ns: int) -> None:
        """Record that run's vehicle observed the landmarks in `slots` at its current pose."""
        vin = run.vin
        p, euler = vin.model.pose(self.state.vehicle_x(vin.name))
        views = _view_dirs(vin, p, euler, self.state.landmarks()[slots])
        self.book.observe(self.book.slot_ids[slots], run.index, stamp_ns, views)

    def _frame(self, run: _VehicleRun, t_ns: int, f: int) -> None:
        t_start = time.perf_counter()
        s = self.settings
        vin = run.vin
        st = self.state
        self._predict(run, t_ns)

        fs = vin.features
        sl = fs.frame_matches(f)
        ml, mr = fs.match_left[sl], fs.match_right[sl]
        z_obs = np.concatenate([fs.left_uv_px[ml], fs.right_uv_px[mr]], axis=1).astype(float)
        desc_obs = fs.left_desc[ml]
        v_idx = st.vehicles[vin.name].index
        x_v = st.x[v_idx]
        p, euler = vin.model.pose(x_v)
        R4 = np.eye(4) * s.pixel_sigma_px**2

        # --- predict the landmarks in view, associate, update (or localise first)
        c = _FrameCounts(
            near=np.zeros(len(z_obs), dtype=bool), used=np.zeros(len(z_obs), dtype=bool)
        )
        localising = run.localised_ns is None
        if localising:
            visible = np.zeros(0, dtype=np.int64)
            self._localise(run, t_ns, z_obs, desc_obs, c)
        else:
            visible = self._visible(vin, p, euler)
            if len(visible) and len(z_obs):
                self._associate_and_update(run, t_ns, visible, z_obs, desc_obs, R4, c)
        updated_slots = c.updated_slots

        # landmark uncertainty of this frame's updated landmarks (before any eviction)
        lm_std = float("nan")
        if len(updated_slots):
            lm_cov = st.landmark_covariances(updated_slots)
            lm_std = float(np.sqrt(np.mean(np.trace(lm_cov, axis1=1, axis2=2))))

        # --- new landmarks (type 3), confirmed by the previous frame's candidates; none
        # while (or in the frame where) the vehicle is being localised
        want = min(s.max_new_per_frame, max(0, s.target_tracked - len(updated_slots)))
        free = ~c.near & ~c.used
        if want and not localising:  # confirming costs an association: only when wanted
            confirmed = self._confirm_candidates(run, sl, z_obs, desc_obs, free, R4)
            if len(confirmed):
                c.type3 = self._add_landmarks(run, t_ns, sl, confirmed, updated_slots, want)
        if run.localised_ns is None:
            run.candidates = None
        else:
            self._new_candidates(run, t_ns, sl, z_obs, free)

        # --- record
        x_v = st.x[v_idx]
        if not (np.all(np.isfinite(x_v)) and np.all(np.isfinite(st.P[np.ix_(v_idx, v_idx)]))):
            self._diverge(vin.name, t_ns, "non-finite state or covariance")
        J = vin.model.pose_jacobian(x_v)
        pose_cov = J @ st.P[np.ix_(v_idx, v_idx)] @ J.T
        p, euler = vin.model.pose(x_v)
        run.stamps.append(t_ns)
        run.x.append(x_v.copy())
        run.pose_cov.append(pose_cov)
        self._check_divergence(run, t_ns, c, len(visible), len(z_obs))
        self.timeline.append(
            {
                "stamp_ns": t_ns,
                "vehicle": vin.name,
                "frame": f,
                "state_size": st.n,
                "landmarks_in_state": st.n_landmarks,
                "landmarks_mapped": self.book.count,
                "matches": len(z_obs),
                "visible": len(visible),
                "rejected": c.rejected,
                "type1": c.type1,
                "type2": c.type2,
                "type3": c.type3,
                "loop_closure": c.loop,
                "localised": run.localised_ns is not None,
                "sigma_pos_m": float(np.sqrt(np.trace(pose_cov[:3, :3]))),
                "sigma_att_rad": float(np.sqrt(np.trace(pose_cov[3:, 3:]))),
                "sigma_landmark_m": lm_std,
                "nis": c.nis,
                "nis_dof": c.dof,
                "gamma": c.gamma,
                "gamma_raised": c.gamma_raised,
                "x_m": float(p[0]),
                "y_m": float(p[1]),
                "z_m": float(p[2]),
                "ms": 1e3 * (time.perf_counter() - t_start),
            }
        )

    def _check_divergence(
        self, run: _VehicleRun, t_ns: int, c: _FrameCounts, n_visible: int, n_obs: int
    ) -> None:
        """Median NIS per measurement over the vehicle's last updates (module docstring)."""
        s = self.settings
        vin = run.vin
        if c.dof:
            run.nis_recent.append(c.nis / c.dof)
        elif n_visible >= MIN_VISIBLE_FOR_LOST and n_obs:
            # landmarks in view, observations there, none inside its window: the
            # innovations are beyond the gate, i.e. larger than any NIS recorded
            run.nis_recent.append(np.inf)
        if c.dof or np.isinf(run.nis_recent[-1] if run.nis_recent else 0.0):
            median_nis = float(np.median(run.nis_recent))
            if len(run.nis_recent) == run.nis_recent.maxlen and median_nis > s.nis_per_dof_max:
                self._diverge(
                    vin.name,
                    t_ns,
                    f"median NIS per measurement {median_nis:.1f} over the last "
                    f"{len(run.nis_recent)} updates (1 expected, limit {s.nis_per_dof_max:g})"
                    + (
                        "; frames where no landmark predicted in view matched inside its "
                        "window count as infinite NIS"
                        if np.isinf(median_nis)
                        else ""
                    ),
                )

    def _associate_and_update(
        self,
        run: _VehicleRun,
        t_ns: int,
        visible: I64,
        z_obs: F64,
        desc_obs: NDArray[np.uint8],
        R4: F64,
        c: _FrameCounts,
    ) -> None:
        """Associate the frame's matches with the landmarks in view, update the state with
        the accepted ones, classify them (type 1 / 2, loop closures) and log events."""
        s = self.settings
        vin = run.vin
        st = self.state
        book = self.book
        fs = vin.features
        v_idx = st.vehicles[vin.name].index
        R_hat = s.filter.r_scale * R4
        pred, P_vv, P_mm = self._predict_slots(vin, visible)
        ids_vis = book.slot_ids[visible]
        assoc = associate(
            pred,
            book.desc[ids_vis],
            z_obs,
            desc_obs,
            s.gate_chi2,
            s.descriptor_ratio,
            s.max_descriptor_distance,
        )
        c.near = assoc.near_landmark
        ok = pose_consistent(
            pred,
            assoc.pred_index,
            z_obs[assoc.match_index],
            P_vv,
            P_mm[assoc.pred_index],
            R_hat,
            s.consistency_chi2,
        )
        c.rejected = int(np.sum(~ok))
        if not ok.any():
            return
        ids = ids_vis[assoc.pred_index[ok]]
        last_v = book.last_seen_ns[ids, run.index]
        seen_before = last_v != NEVER
        absent_ns = np.where(seen_before, t_ns - last_v, 0)
        order = spread_order(
            z_obs[assoc.match_index[ok], :2], -absent_ns.astype(float), tuple(fs.rig.size_px[0])
        )[: s.max_updates_per_frame]
        a_pred = assoc.pred_index[ok][order]
        a_match = assoc.match_index[ok][order]
        ids, seen_before, absent_ns = ids[order], seen_before[order], absent_ns[order]
        k = len(order)
        res = self._stacked_update(v_idx, pred, a_pred, z_obs[a_match])
        c.nis, c.dof = res.nis, 4 * k
        c.gamma, c.gamma_raised = res.gamma, res.gamma_raised
        c.updated_slots = visible[a_pred]
        c.used[a_match] = True
        c.type2 = int(np.sum(~seen_before))
        c.type1 = k - c.type2
        loops = seen_before & (absent_ns > s.loop_closure_gap_ns)
        c.loop = int(loops.sum())
        self._observe(run, c.updated_slots, t_ns)
        if c.loop >= s.loop_closure_min_landmarks:
            self._event(t_ns, "loop_closure", vin.name, "", c.loop, absent_ns[loops])
        if c.type2:
            others = self._other_observers(ids[~seen_before], run.index)
            self._event(t_ns, "cross_vehicle", vin.name, others, c.type2, absent_ns[~seen_before])

    def _predict_slots(self, vin: VehicleInput, slots: I64) -> tuple[LandmarkPrediction, F64, F64]:
        """The landmarks in `slots` predicted into vin's images with their innovation
        covariances; also P_vv (n_v, n_v) and P_mm (k, 3, 3)."""
        st = self.state
        v_idx = st.vehicles[vin.name].index
        x_v = st.x[v_idx]
        p, euler = vin.model.pose(x_v)
        lm_idx = st.landmark_index(slots)  # (k, 3)
        P_vv = st.P[np.ix_(v_idx, v_idx)]
        P_vm = st.P[v_idx[:, None, None], lm_idx[None, :, :]].transpose(1, 0, 2)
        P_mm = st.P[lm_idx[:, :, None], lm_idx[:, None, :]]
        R_hat = self.settings.filter.r_scale * np.eye(4) * self.settings.pixel_sigma_px**2
        pred = predict_landmarks(
            vin.obs, p, euler, vin.model.pose_jacobian(x_v), slots, st.landmarks()[slots],
            P_vv, P_vm, P_mm, R_hat,
        )  # fmt: skip
        return pred, P_vv, P_mm

    def _stacked_update(
        self, v_idx: I64, pred: LandmarkPrediction, rows: I64, z: F64
    ) -> UpdateResult:
        """One update (eq. 19) with observations z (k, 4) of the predicted landmarks
        `pred` rows `rows` (k,): H touches the vehicle block and each landmark's 3 columns."""
        s = self.settings
        k, nv = len(rows), len(v_idx)
        H_lm = np.zeros((k, 4, k, 3))  # landmark j's rows touch only its columns
        H_lm[np.arange(k), :, np.arange(k), :] = pred.H_m[rows]
        H = np.concatenate([pred.H_v[rows].reshape(4 * k, nv), H_lm.reshape(4 * k, 3 * k)], axis=1)
        cols = np.concatenate([v_idx, self.state.landmark_index(pred.slots[rows]).reshape(-1)])
        R = np.kron(np.eye(k), np.eye(4) * s.pixel_sigma_px**2)
        # NH-infinity's bound is on the vehicles whose pose is known (a vehicle still being
        # localised has a prior far wider than gamma: bounding it would inflate it at every
        # other vehicle's update)
        known = [n for n, r in self.runs.items() if r.localised_ns is not None]
        res = self.state.update(
            s.filter, z.reshape(-1), pred.z[rows].reshape(-1), H, cols, R, vehicles=known
        )
        self.gamma_raised += int(res.gamma_raised)
        return res

    def _localise(
        self,
        run: _VehicleRun,
        t_ns: int,
        z_obs: F64,
        desc_obs: NDArray[np.uint8],
        c: _FrameCounts,
    ) -> None:
        """Try to localise a vehicle whose pose is not known yet in the landmarks of the
        state (`localise.py`). On success, and if the pose found is inside the vehicle's
        prior (chi-square gate on position), the vehicle is relinearised at that pose (its
        covariance, the broad prior, is kept) and updated with the inlier landmarks: from
        then on it is an ordinary vehicle."""
        s = self.settings
        st = self.state
        vin = run.vin
        if st.n_landmarks < s.localise_min_inliers or len(z_obs) < s.localise_min_inliers:
            return
        book = self.book
        found = localise(
            vin.obs, z_obs, desc_obs, st.landmarks(), book.desc[book.slot_ids],
            ratio=s.descriptor_ratio, max_descriptor_distance=s.max_descriptor_distance,
            reprojection_px=s.localise_reprojection_px, min_inliers=s.localise_min_inliers,
            seed=len(run.stamps),
        )  # fmt: skip
        if found is None:
            return
        v_idx = st.vehicles[vin.name].index
        x_v = st.x[v_idx]
        p_prior, euler_prior = vin.model.pose(x_v)
        J = vin.model.pose_jacobian(x_v)
        cov_p = (J @ st.P[np.ix_(v_idx, v_idx)] @ J.T)[:3, :3]
        d = found.p_nav_m - p_prior
        d2 = float(d @ np.linalg.solve(cov_p, d))
        if d2 > s.localise_prior_chi2:
            c.rejected = len(found.match_rows)
            return
        # angles continuous with the state's (which are not wrapped)
        euler = euler_prior + (found.euler_rad - euler_prior + np.pi) % (2 * np.pi) - np.pi
        st.x[v_idx] = vin.model.with_pose(x_v, found.p_nav_m, euler)
        slots = found.landmark_rows
        pred, _, _ = self._predict_slots(vin, slots)
        rows = np.arange(len(slots))
        res = self._stacked_update(v_idx, pred, rows, z_obs[found.match_rows])
        k = len(slots)
        c.nis, c.dof = res.nis, 4 * k
        c.gamma, c.gamma_raised = res.gamma, res.gamma_raised
        c.updated_slots = slots
        c.used[found.match_rows] = True
        ids = book.slot_ids[slots]
        c.type2 = k
        others = self._other_observers(ids, run.index)
        self._observe(run, slots, t_ns)
        run.localised_ns = t_ns
        after_s = (t_ns - vin.start_ns) * 1e-9
        self._event(
            t_ns, "localisation", vin.name, others, k, np.zeros(0, dtype=np.int64),
            f"localised {after_s:.2f} s after its start: PnP on {k} of {found.candidates} "
            f"descriptor pairs, reprojection RMS {found.rms_px:.2f} px, moved "
            f"{np.linalg.norm(d):.1f} m from its prior",
        )  # fmt: skip

    def _valid_points(self, run: _VehicleRun, sl: slice) -> NDArray[np.bool_]:
        """(M,) matches whose triangulated point can start a landmark: finite, in front, and
        depth standard deviation below `max_new_depth_sigma_ratio` of the depth."""
        fs = run.vin.features
        depth = fs.match_p_cam_m[sl][:, 2]
        sig = np.sqrt(np.maximum(fs.match_cov_cam_m2[sl][:, 2, 2], 0.0))
        with np.errstate(invalid="ignore"):
            return (
                np.isfinite(depth)
                & (depth > 0)
                & (sig < self.settings.max_new_depth_sigma_ratio * depth)
            )

    def _confirm_candidates(
        self,
        run: _VehicleRun,
        sl: slice,
        z_obs: F64,
        desc_obs: NDArray[np.uint8],
        free: NDArray[np.bool_],
        R4: F64,
    ) -> I64:
        """Matches of this frame (indices into it) that re-observe a candidate of the
        vehicle's previous frame: predicted with the current pose, inside the candidate's
        window (its covariance and the pixel noise), passing the descriptor ratio test. A
        landmark is only created from a point seen twice: a wrong stereo match (a random
        pairing) is not seen again, so it never enters the map."""
        cand = run.candidates
        idx = np.flatnonzero(free & self._valid_points(run, sl))
        if cand is None or len(cand.m) == 0 or len(idx) == 0:
            return np.zeros(0, dtype=np.int64)
        m_c, cov_c, desc_c = cand.m, cand.cov, cand.desc
        vin = run.vin
        x_v = self.state.vehicle_x(vin.name)
        p, euler = vin.model.pose(x_v)
        ok = _in_view(vin, p, euler, m_c)
        if len(ok) == 0:
            return np.zeros(0, dtype=np.int64)
        z, _, H_m = vin.obs.predict(p, euler, m_c[ok])
        S = H_m @ cov_c[ok] @ np.swapaxes(H_m, 1, 2) + R4
        pred = LandmarkPrediction(ok, z, H_m, H_m, S)
        s = self.settings
        assoc = associate(
            pred, desc_c[ok], z_obs[idx], desc_obs[idx], s.gate_chi2, s.descriptor_ratio,
            s.max_descriptor_distance,
        )  # fmt: skip
        return idx[assoc.match_index]

    def _new_candidates(
        self, run: _VehicleRun, t_ns: int, sl: slice, z_obs: F64, free: NDArray[np.bool_]
    ) -> None:
        """This frame's free matches become the candidates the next frame may confirm."""
        fs = run.vin.features
        idx = np.flatnonzero(free & self._valid_points(run, sl))
        vin = run.vin
        v_idx = self.state.vehicles[vin.name].index
        x_v = self.state.x[v_idx]
        p, euler = vin.model.pose(x_v)
        J = vin.model.pose_jacobian(x_v)
        pose_cov = J @ self.state.P[np.ix_(v_idx, v_idx)] @ J.T
        m, cov = vin.obs.landmark_from_camera_point(
            p, euler, fs.match_p_cam_m[sl][idx], fs.match_cov_cam_m2[sl][idx], pose_cov
        )
        run.candidates = _Candidates(m, cov, fs.left_desc[fs.match_left[sl]][idx], z_obs[idx], t_ns)

    def _add_landmarks(
        self,
        run: _VehicleRun,
        t_ns: int,
        sl: slice,
        cand: I64,
        protected: I64,
        want: int,
    ) -> int:
        """Initialise up to `want` of the matches `cand` (confirmed candidates, spread over
        the image, the most precise first) as landmarks (inverse model, with covariance and
        cross-covariance from the pose), evicting landmarks when the state is full."""
        st = self.state
        vin = run.vin
        fs = vin.features
        pc = fs.match_p_cam_m[sl]
        cov_c = fs.match_cov_cam_m2[sl]
        depth = pc[cand, 2]
        sig = np.sqrt(np.maximum(cov_c[cand, 2, 2], 0.0))
        uv = fs.left_uv_px[fs.match_left[sl]][cand].astype(float)
        pick = cand[spread_order(uv, sig / depth, tuple(fs.rig.size_px[0]))[:want]]
        # room in the state
        bound = self.max_landmarks
        over = st.n_landmarks + len(pick) - bound
        if over > 0:
            slots_all = np.arange(st.n_landmarks)
            covs = st.landmark_covariances(slots_all)
            latest = np.array(
                [r.stamps[-1] if r.stamps and r is not run else NEVER for r in self.runs.values()],
                dtype=np.int64,
            )
            order = self.book.eviction_order(protected, np.trace(covs, axis1=1, axis2=2), latest)
            evict = order[: max(over, bound // 10)]  # in batches: fewer copies
            self.book.store_estimates(evict, st.landmarks()[evict], covs[evict])
            kept = st.remove_landmarks(evict)
            self.book.keep_slots(kept)
            pick = pick[: max(0, bound - st.n_landmarks)]
        if len(pick) == 0:
            return 0
        v_idx = st.vehicles[vin.name].index
        x_v = st.x[v_idx]
        p, euler = vin.model.pose(x_v)
        J = vin.model.pose_jacobian(x_v)
        m, J_pose, J_pc = vin.obs.landmark_jacobians(p, euler, pc[pick])
        k = len(pick)
        Jx = (J_pose @ J).reshape(3 * k, len(v_idx))  # d m / d x_v, (3k, n_v)
        P_mx = Jx @ st.P[v_idx, :]
        P_mm = P_mx[:, v_idx] @ Jx.T
        meas = J_pc @ cov_c[pick] @ J_pc.T  # (k, 3, 3)
        for j in range(k):
            P_mm[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += meas[j]
        slots = st.add_landmarks(m, P_mm, P_mx)
        self.book.add(
            fs.left_desc[fs.match_left[sl]][pick],
            run.index,
            t_ns,
            fs.match_landmark_id[sl][pick],
            _view_dirs(vin, p, euler, m),
        )
        for other in self.runs.values():
            if other is not run:
                self._joint_initialisation(run, other, t_ns, slots)
        return k

    def _joint_initialisation(
        self, run: _VehicleRun, other: _VehicleRun, t_ns: int, slots: I64
    ) -> None:
        """New landmarks of `run` that `other` saw at about the same time (among the
        unmatched points of its last frame, within `joint_init_window_ns`) are initialised
        from both: `other`'s observation updates them right away. Its state is still at that
        frame (a vehicle's state moves only at its own frames), so the update is exact (the
        paper: a new landmark seen by several vehicles is initialised from all of them)."""
        s = self.settings
        cand = other.candidates
        if cand is None or not len(cand.m) or t_ns - cand.stamp_ns > s.joint_init_window_ns:
            return
        st = self.state
        vin = other.vin
        v_idx = st.vehicles[vin.name].index
        x_v = st.x[v_idx]
        p, euler = vin.model.pose(x_v)
        front = _in_view(vin, p, euler, st.landmarks()[slots])
        if not len(front):
            return
        pred, _, _ = self._predict_slots(vin, slots[front])
        ids = self.book.slot_ids[slots[front]]
        assoc = associate(
            pred, self.book.desc[ids], cand.z, cand.desc, s.gate_chi2, s.descriptor_ratio,
            s.max_descriptor_distance,
        )  # fmt: skip
        k = len(assoc.pred_index)
        if not k:
            return
        a = assoc.pred_index
        self._stacked_update(v_idx, pred, a, cand.z[assoc.match_index])
        self._observe(other, slots[front][a], cand.stamp_ns)
        other.candidates = cand.without(assoc.match_index)
        self._event(
            t_ns, "joint_initialisation", run.vin.name, vin.name, k, np.zeros(0, dtype=np.int64)
        )

    def _other_observers(self, ids: I64, vehicle: int) -> str:
        bits = int(np.bitwise_or.reduce(self.book.observers[ids])) & ~(1 << vehicle)
        return ";".join(n for i, n in enumerate(self.names) if bits >> i & 1)

    def _event(
        self,
        t_ns: int,
        kind: str,
        vehicle: str,
        others: str,
        count: int,
        absent_ns: I64,
        detail: str = "",
    ) -> None:
        """Log an event; frames of the same vehicle with the same kind of event (and the same
        other vehicles) less than `event_merge_ns` apart are one event: one loop closure or
        one encounter, counted over its frames."""
        absence = float(np.max(absent_ns)) * 1e-9 if len(absent_ns) else 0.0
        key = (kind, vehicle, others)
        last = self._open_events.get(key)
        if last is not None and t_ns - last["end_stamp_ns"] <= self.settings.event_merge_ns:
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
        self.events.append(row)
        self._open_events[key] = row

    def _diverge(self, vehicle: str, t_ns: int, reason: str) -> None:
        if self.divergence is None:
            self.divergence = Divergence(vehicle, t_ns, reason)
            self._event(t_ns, "divergence", vehicle, "", 0, np.zeros(0, dtype=np.int64), reason)

    # ------------------------------------------------------------------ result
    def _result(self) -> SlamResult:
        st, book = self.state, self.book
        if st.n_landmarks:
            slots = np.arange(st.n_landmarks)
            book.store_estimates(slots, st.landmarks(), st.landmark_covariances(slots))
        n = book.count
        in_state = np.zeros(n, dtype=bool)
        in_state[book.slot_ids] = True
        last_seen = book.last_seen_ns[:n].max(axis=1) if n else np.zeros(0, dtype=np.int64)
        lm = LandmarkMap(
            landmark_id=np.arange(n),
            p_nav_m=book.p_nav_m[:n].copy(),
            std_m=book.std_m[:n].copy(),
            observers=book.observer_names(self.names),
            n_observations=book.n_obs[:n].copy(),
            first_seen_ns=book.first_seen_ns[:n].copy(),
            last_seen_ns=last_seen,
            in_state=in_state,
            true_id=book.true_id[:n].copy(),
        )
        tracks = {}
        for name, r in self.runs.items():
            model = r.vin.model
            X = np.array(r.x).reshape(-1, model.n)
            poses = [model.pose(x) for x in X]
            tracks[name] = VehicleTrack(
                name,
                np.asarray(r.stamps, dtype=np.int64),
                X,
                np.array([q[0] for q in poses]).reshape(-1, 3),
                np.array([q[1] for q in poses]).reshape(-1, 3),
                np.array(r.pose_cov).reshape(-1, 6, 6),
            )
        return SlamResult(
            tracks, self.timeline, self.events, lm, self.divergence, self.gamma_raised
        )


def _in_view(vin: VehicleInput, p: F64, euler: F64, m_nav_m: F64) -> I64:
    """Rows of landmarks m (k, 3) predicted in front of vin's cameras at (p, Psi) and inside
    both images (a point near the camera plane projects far outside: its Jacobian would
    blow up the innovation covariance)."""
    if not len(m_nav_m):
        return np.zeros(0, dtype=np.int64)
    depth = camera_depths(vin.obs, p, euler, m_nav_m)
    front = np.flatnonzero(depth > 0)
    if not len(front):
        return front
    z_pred, _, _ = vin.obs.predict(p, euler, m_nav_m[front])
    return front[in_view(z_pred, depth[front], vin.features.rig.size_px)]


def _view_dirs(vin: VehicleInput, p: F64, euler: F64, m_nav_m: F64) -> F64:
    """(k, 3) unit vectors from landmarks m (k, 3) to vin's left camera centre at (p, Psi)."""
    centre = p + euler_zyx_to_matrix(*euler) @ vin.obs.t_body_cam[0]
    d = centre - np.atleast_2d(m_nav_m)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


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
    timeline and events in time order, the maps concatenated with ids renumbered."""
    maps = [r.landmarks for r in results]
    offsets = np.cumsum([0] + [len(m) for m in maps])
    lm = LandmarkMap(
        landmark_id=np.arange(int(offsets[-1])),
        p_nav_m=np.concatenate([m.p_nav_m for m in maps]).reshape(-1, 3),
        std_m=np.concatenate([m.std_m for m in maps]).reshape(-1, 3),
        observers=tuple(o for m in maps for o in m.observers),
        n_observations=np.concatenate([m.n_observations for m in maps]),
        first_seen_ns=np.concatenate([m.first_seen_ns for m in maps]),
        last_seen_ns=np.concatenate([m.last_seen_ns for m in maps]),
        in_state=np.concatenate([m.in_state for m in maps]),
        true_id=np.concatenate([m.true_id for m in maps]),
    )
    divergences = [r.divergence for r in results if r.divergence is not None]
    return SlamResult(
        tracks={k: v for r in results for k, v in r.tracks.items()},
        timeline=sorted((row for r in results for row in r.timeline), key=lambda x: x["stamp_ns"]),
        events=sorted((e for r in results for e in r.events), key=lambda x: x["stamp_ns"]),
        landmarks=lm,
        divergence=min(divergences, key=lambda d: d.stamp_ns) if divergences else None,
        gamma_raised=sum(r.gamma_raised for r in results),
    )
