"""Cooperation: what makes one filter over several vehicles more than several filters.

- Joint initialisation (paper: a new landmark seen by several vehicles at once is
  initialised from all of them): new landmarks of one vehicle that another saw at about the
  same time (among the unmatched points of its last frame, within `joint_init_window_ns`;
  another vehicle's landmark, so `other_vehicle_descriptor_ratio` with its second-best over
  all those points) are updated with that observation right away, after the same test of
  one consistent correction of the observing vehicle's pose as its own frames' associations
  (`association.pose_consistent`). The other vehicle's state is still at that frame (a
  vehicle's state moves only at its own frames), so the update is exact.
  `fuse.map.joint_initialisation` false turns it off (the slam loop does not call it).
- Localisation of a vehicle whose initial pose is unknown (extension beyond the paper) in
  the landmarks the others mapped: `unknown_pose.py`.
- NH-infinity's bound is put on the vehicles whose pose is known (`bounded_vehicles`): a
  vehicle still being localised has a prior far wider than gamma, and bounding it would
  inflate it at every other vehicle's update.
- Type-2 observations (`association.classify`) and these steps are logged as events.
"""

from __future__ import annotations

from cvslam_cli.estimation.association import (
    associate,
    in_view_rows,
    lookalike_gates,
    noise_scale,
    pose_consistent,
    record_observations,
    view_rays,
)
from cvslam_cli.estimation.events import EventLog
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
        m = self.state.landmarks(slots)
        front = in_view_rows(vin, pose.p_nav_m, pose.euler_rad, m)
        _, distance = view_rays(vin, pose.p_nav_m, pose.euler_rad, m[front])
        ids = self.book.slot_ids[slots[front]]
        near = self.book.ids_within_distance(
            ids, other.index, distance, s.other_vehicle_max_distance_ratio
        )
        front, ids = front[near], ids[near]
        if not len(front):
            return
        scale = noise_scale(self.book, ids, other.index, s.other_vehicle_noise_ratio)
        pred, errors = self.updater.predict(pose, slots[front], scale)
        gates = lookalike_gates(
            self.book, ids, other.index, pred.S, s.gate_chi2, s.other_vehicle_lookalike_bound
        )
        assoc = associate(
            pred, self.book.desc[ids], cand.z, cand.desc, s.gate_chi2,
            s.other_vehicle_descriptor_ratio, s.max_descriptor_distance,
            s.other_vehicle_ratio_over_frame, gates,
        )  # fmt: skip
        if not len(assoc.pred_index):
            return
        ok = pose_consistent(
            pred, assoc.pred_index, cand.z[assoc.match_index], pose.P_vv,
            errors, self.updater.R_pixel_hat, s.consistency_chi2,
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
