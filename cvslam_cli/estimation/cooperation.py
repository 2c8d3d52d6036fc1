"""Cooperation: what makes one filter over several vehicles more than several filters.

- Joint initialisation (paper: a new landmark seen by several vehicles at once is
  initialised from all of them): new landmarks of one vehicle that another saw at about the
  same time (among the unmatched points of its last frame, within `joint_init_window_ns`)
  are updated with that observation right away, after the same test of one consistent
  correction of the observing vehicle's pose as its own frames' associations
  (`association.pose_consistent`). The other vehicle's state is still at that frame (a
  vehicle's state moves only at its own frames), so the update is exact.
- Localisation of a vehicle whose initial pose is unknown (extension beyond the paper):
  each of its frames is matched to the landmarks in the state (`localise.py`, PnP); once
  found, and inside the vehicle's prior (chi-square gate on position), the vehicle is
  relinearised at that pose (its covariance, the broad prior, is kept) and updated with
  the inlier landmarks: from then on it is an ordinary vehicle.
- NH-infinity's bound is put on the vehicles whose pose is known (`bounded_vehicles`): a
  vehicle still being localised has a prior far wider than gamma, and bounding it would
  inflate it at every other vehicle's update.
- Type-2 observations (`association.classify`) and these steps are logged as events.
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.association import (
    TYPE_2,
    associate,
    classify,
    in_view_rows,
    pose_consistent,
    record_observations,
    unassociated,
)
from cvslam_cli.estimation.events import EventLog
from cvslam_cli.estimation.frame import FrameMatches, FrameOutcome
from cvslam_cli.estimation.localise import localise
from cvslam_cli.estimation.mapping import LandmarkBook
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.update import VisualUpdater
from cvslam_cli.estimation.vehicle import VehiclePose, VehicleRun
from cvslam_cli.records.arrays import I64


class Cooperation:
    """The cooperative steps (module docstring) over the vehicles `runs` (in vehicle order)
    sharing `state` and `book`."""

    def __init__(
        self,
        state: JointState,
        book: LandmarkBook,
        runs: list[VehicleRun],
        updater: VisualUpdater,
        events: EventLog,
        settings: SlamSettings,
    ) -> None:
        self.state = state
        self.book = book
        self.runs = runs
        self.updater = updater
        self.events = events
        self.settings = settings
        self.names = [r.vin.name for r in runs]

    def bounded_vehicles(self) -> list[str]:
        """The vehicles NH-infinity's bound is put on: those whose pose is known."""
        return [r.vin.name for r in self.runs if r.localised]

    def joint_initialisation(self, run: VehicleRun, slots: I64, t_ns: int) -> None:
        """Update run's new landmarks `slots` with the other vehicles' candidates (module
        docstring)."""
        for other in self.runs:
            if other is not run:
                self._joint_initialisation(run, other, slots, t_ns)

    def _joint_initialisation(
        self, run: VehicleRun, other: VehicleRun, slots: I64, t_ns: int
    ) -> None:
        s = self.settings
        cand = other.candidates
        if cand is None or not len(cand.m) or t_ns - cand.stamp_ns > s.joint_init_window_ns:
            return
        vin = other.vin
        pose = VehiclePose.of(self.state, vin)
        front = in_view_rows(vin, pose.p_nav_m, pose.euler_rad, self.state.landmarks(slots))
        if not len(front):
            return
        pred, P_mm = self.updater.predict(vin, pose, slots[front])
        ids = self.book.slot_ids[slots[front]]
        assoc = associate(
            pred, self.book.desc[ids], cand.z, cand.desc, s.gate_chi2, s.descriptor_ratio,
            s.max_descriptor_distance,
        )  # fmt: skip
        if not len(assoc.pred_index):
            return
        ok = pose_consistent(
            pred, assoc.pred_index, cand.z[assoc.match_index], pose.P_vv,
            P_mm[assoc.pred_index], self.updater.R_pixel_hat, s.consistency_chi2,
        )  # fmt: skip
        a, rows = assoc.pred_index[ok], assoc.match_index[ok]
        k = len(a)
        if not k:
            return
        self.updater.update(pose.index, pred, a, cand.z[rows], self.bounded_vehicles())
        record_observations(
            self.state, self.book, other, slots[front][a], cand.stamp_ns, cand.z[rows]
        )  # fmt: skip
        other.candidates = cand.without(rows)
        self.events.add(t_ns, "joint_initialisation", run.vin.name, vin.name, k)

    def localise_vehicle(self, run: VehicleRun, frame: FrameMatches) -> FrameOutcome:
        """Try to localise run's vehicle (pose unknown) in the landmarks of the state from
        this frame (module docstring)."""
        s = self.settings
        st = self.state
        vin = run.vin
        book = self.book
        n = len(frame)
        out = FrameOutcome(unassociated(n).type)
        if st.n_landmarks < s.localise_min_inliers or n < s.localise_min_inliers:
            return out
        found = localise(
            vin.obs, frame.z, frame.desc, st.landmarks(), book.desc[book.slot_ids],
            ratio=s.descriptor_ratio, max_descriptor_distance=s.max_descriptor_distance,
            reprojection_px=s.localise_reprojection_px, min_inliers=s.localise_min_inliers,
            seed=len(run.stamps_ns),
        )  # fmt: skip
        if found is None:
            return out
        prior = VehiclePose.of(st, vin)
        d = found.p_nav_m - prior.p_nav_m
        d2 = float(d @ np.linalg.solve(prior.cov[:3, :3], d))
        if d2 > s.localise_prior_chi2:
            out.rejected = len(found.match_rows)
            return out
        # angles continuous with the state's (which are not wrapped)
        e0 = prior.euler_rad
        euler = e0 + (found.euler_rad - e0 + np.pi) % (2 * np.pi) - np.pi
        st.x[prior.index] = vin.model.with_pose(prior.x, found.p_nav_m, euler)
        slots = found.landmark_rows
        pose = VehiclePose.of(st, vin)  # relinearised
        pred, _ = self.updater.predict(vin, pose, slots)
        rows = np.arange(len(slots))
        res = self.updater.update(
            pose.index, pred, rows, frame.z[found.match_rows], self.bounded_vehicles()
        )
        k = len(slots)
        ids = book.slot_ids[slots]
        types = classify(
            np.zeros(n, dtype=bool), found.match_rows, book.last_seen_ns[ids, run.index],
            frame.stamp_ns, s.loop_closure_gap_ns,
        )  # fmt: skip
        out = FrameOutcome(
            types.type, slots, type2=types.count(TYPE_2), nis=res.nis, dof=4 * k, gamma=res.gamma,
            gamma_raised=res.gamma_raised,
        )  # fmt: skip
        others = book.other_observers(ids, run.index, self.names)
        record_observations(
            self.state, self.book, run, slots, frame.stamp_ns, frame.z[found.match_rows]
        )
        run.localised_ns = frame.stamp_ns
        after_s = (frame.stamp_ns - vin.start_ns) * 1e-9
        self.events.add(
            frame.stamp_ns, "localisation", vin.name, others, k, None,
            f"localised {after_s:.2f} s after its start: PnP on {k} of {found.candidates} "
            f"descriptor pairs, reprojection RMS {found.rms_px:.2f} px, moved "
            f"{np.linalg.norm(d):.1f} m from its prior",
        )  # fmt: skip
        return out
