"""Re-activation: landmarks evicted from the state brought back when a vehicle sees them again.

The state holds a bounded number of landmarks (`settings.landmark_bound`); the others keep
their last nav-frame estimate and marginal covariance in the book (`mapping.py`). Without
re-activation a vehicle returning to ground mapped long ago (by itself: a loop; by another
vehicle: a type-2 encounter) finds nothing there and maps it anew, so no loop is ever closed
once the bound is reached (BENCHMARKS.md, "Fuse: cooperative, 2 and 4 vehicles").

Finding them (`Reactivation.find`), at each frame of a localised vehicle, among the
landmarks out of the state that nobody has observed for at least `reactivation_min_absence_ns`
(so a landmark just evicted by the bound does not bounce straight back) and whose position
is known to `MAX_REACTIVATION_STD_M`:
1. predicted in view: in front of the cameras, inside both images, within the maximum
   viewing angle of its mean viewing direction (as for the state's landmarks);
2. predicted pixel and innovation covariance from the vehicle's pose covariance and the
   landmark's inflated marginal (below), S = H_v P_vv H_v^T + H_m (k C) H_m^T + R_hat, and the
   chi-square gate with the descriptor ratio test against the frame's matches that no
   landmark in the state claims (`association.associate`; another vehicle's landmark that
   this one never observed with `other_vehicle_descriptor_ratio` and, with
   `other_vehicle_ratio_over_frame`, its second-best over all those matches, as in the
   frame's own association);
3. the matches agree with one vehicle correction (`association.pose_consistent`), and at
   least `reactivation_min_landmarks` of them do (one look-alike in a window is no loop).
Place recognition by appearance alone (when the pose is too uncertain for the windows) is
not done: a vehicle whose pose drifted beyond the gate does not re-activate.

Bringing them back (`Reactivation.reinsert`) conservatively: the archived estimate was
correlated with the state when it was evicted, and marginalisation dropped that
cross-covariance, so the true joint covariance of (state, landmark) is [[P, X], [X^T, C]]
with an unknown X. Re-inserting (m, C) with X = 0 would count the information the landmark
shares with the state twice and make the filter overconfident. It is re-inserted with zero
cross-covariance but its marginal inflated by `reactivation_inflation` k >= 1, i.e. a
covariance k C: the covariance-intersection bound [[P / w, 0], [0, C / (1 - w)]] with the
state's weight w -> 1 taken on the landmark alone (the state, whose correlations are
known, is left as it is), k = 1 / (1 - w). With the observability constraint
(`fuse.observability_constrained`, `gauge.py`) the landmark comes back with the gauge rows
it had when it left and correlated only with the gauge error the states of the vehicles
of its group read (those linked to its observers by landmarks they observed:
`gauge.gauge_correlated`, `observer_groups`): its inflated marginal as before, and nothing
about where the team is or which way it faces, nor about a vehicle its group never met.
The NEES of the Monte Carlo (`tests/estimation/test_reactivation.py`, BENCHMARKS.md "Fuse:
re-activation") is the check that this is conservative enough. Anchored inverse-depth
landmarks are written relative to a fresh clone of the vehicle's pose
(`JointState.add_anchor`): theta = f(m, anchor) with m independent of the anchor, so the
nav-frame point keeps exactly the covariance k C.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.association import (
    LandmarkErrors,
    LandmarkPrediction,
    associate,
    descriptor_tests,
    in_view_rows,
    lookalike_gates,
    noise_scale,
    pose_consistent,
    scaled_noise,
    view_rays,
)
from cvslam_cli.estimation.frame import FrameMatches
from cvslam_cli.estimation.gauge import gauge_correlated
from cvslam_cli.estimation.landmark_coordinates import AnchoredInverseDepth
from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehiclePose, VehicleRun
from cvslam_cli.records.arrays import F64, I64

# An archived landmark whose position standard deviation exceeds this (m) is not brought
# back: it cannot correct a pose, and one near infinity (an inverse depth at its floor) has
# a covariance so large that its innovation covariance is singular in floating point.
MAX_REACTIVATION_STD_M = 10.0


@dataclass(frozen=True, eq=False)
class Found:
    """Archived landmarks found in a frame: `ids` (k,) book ids, `match_rows` (k,) the frame's
    matches they were associated with, `absent_ns` (k,) since anyone last observed them."""

    ids: I64
    match_rows: I64
    absent_ns: I64


class Reactivation:
    """Finding evicted landmarks in a frame and re-inserting them (module docstring) on
    `state` and `book`, with the filter's pixel noise `R_pixel_hat` (4, 4)."""

    def __init__(
        self, state: JointState, book: LandmarkBook, settings: SlamSettings, R_pixel_hat: F64
    ) -> None:
        self.state = state
        self.book = book
        self.settings = settings
        self.R_pixel_hat = R_pixel_hat

    @property
    def enabled(self) -> bool:
        return self.settings.reactivation

    def inflated_cov(self, ids: I64) -> F64:
        """(k, 3, 3) the archived covariances of the landmarks `ids`, inflated for their
        lost correlation (module docstring)."""
        return self.settings.reactivation_inflation * self.book.cov_nav_m2[ids]

    def archived(self, t_ns: int, min_absence_ns: int | None = None) -> I64:
        """Ids of the landmarks out of the state nobody observed for `min_absence_ns`
        (default: `reactivation_min_absence_ns`)."""
        book = self.book
        n = book.count
        out = ~book.in_state_mask()
        last = book.last_seen_ns[:n].max(axis=1)
        if min_absence_ns is None:
            min_absence_ns = self.settings.reactivation_min_absence_ns
        old = (last != NEVER) & (t_ns - last >= min_absence_ns)
        known = book.known(np.arange(n), MAX_REACTIVATION_STD_M)
        return np.flatnonzero(out & old & known)

    def find(self, run: VehicleRun, frame: FrameMatches, free: NDArray[np.bool_]) -> Found:
        """The archived landmarks that the frame's `free` matches (M,) re-observe."""
        s = self.settings
        none = Found(*(np.zeros(0, dtype=np.int64),) * 3)
        idx = np.flatnonzero(free)
        ids = self.archived(frame.stamp_ns) if len(idx) else np.zeros(0, dtype=np.int64)
        if not len(ids):
            return none
        vin, book = run.vin, self.book
        pose = VehiclePose.of(self.state, vin)
        p, euler = pose.p_nav_m, pose.euler_rad
        ids = ids[in_view_rows(vin, p, euler, book.p_nav_m[ids])]
        if not len(ids):
            return none
        views, distance = view_rays(vin, p, euler, book.p_nav_m[ids])
        ids = ids[
            book.ids_viewable(
                ids, run.index, views, distance, np.cos(s.max_view_angle_rad),
                s.other_vehicle_max_distance_ratio,
            )
        ]  # fmt: skip
        if not len(ids):
            return none
        C = self.inflated_cov(ids)
        z, H_pose, H_m = pose.obs.predict(p, euler, book.p_nav_m[ids])
        H_v = pose.vehicle_jacobian(H_pose)
        scale = noise_scale(book, ids, run.index, s.other_vehicle_noise_ratio)
        S = (
            H_v @ pose.P_vv @ np.swapaxes(H_v, 1, 2)
            + H_m @ C @ np.swapaxes(H_m, 1, 2)
            + scaled_noise(self.R_pixel_hat, scale)
        )
        pred = LandmarkPrediction(ids, z, H_v, H_m, S, noise_scale=scale)
        ratio, frame_wide = descriptor_tests(
            book, ids, run.index, s.descriptor_ratio, s.other_vehicle_descriptor_ratio,
            s.other_vehicle_ratio_over_frame,
        )  # fmt: skip
        gates = lookalike_gates(
            book, ids, run.index, S, s.gate_chi2, s.other_vehicle_lookalike_bound
        )
        assoc = associate(
            pred, book.desc[ids], frame.z[idx], frame.desc[idx], s.gate_chi2, ratio,
            s.max_descriptor_distance, frame_wide, gates,
        )  # fmt: skip
        if len(assoc.pred_index) < s.reactivation_min_landmarks:
            return none
        rows = idx[assoc.match_index]
        ok = pose_consistent(
            pred, assoc.pred_index, frame.z[rows], pose.P_vv,
            LandmarkErrors.independent(C, len(pose.index)),
            self.R_pixel_hat, s.consistency_chi2,
        )  # fmt: skip
        if ok.sum() < s.reactivation_min_landmarks:
            return none
        order = np.argsort(assoc.d2[ok])[: s.max_reactivated_per_frame]  # the closest first
        found = ids[assoc.pred_index[ok][order]]
        last = book.last_seen_ns[found].max(axis=1)
        return Found(found, rows[ok][order], frame.stamp_ns - last)

    def reinsert(self, run: VehicleRun, ids: I64) -> I64:
        """Put the archived landmarks `ids` back into the state with the inflated marginal
        and no cross-covariance (module docstring); the state must have room. Returns their
        slots."""
        st, book = self.state, self.book
        m = book.p_nav_m[ids]
        C = self.inflated_cov(ids)
        k = len(ids)
        # with a gauge (gauge.py): the rows the landmark had when it left; it moves with the
        # team's position and heading as it did then
        N_m = None if st.N is None else book.gauge_nav[ids, :, : st.N.shape[1]]
        if st.coords.anchored:
            slots = _anchored(st, run, m, C, N_m, observer_groups(st, book, ids))
        elif N_m is None:
            P_mm = np.zeros((3 * k, 3 * k))
            for j in range(k):
                P_mm[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = C[j]
            slots = st.add_landmarks(m, P_mm, np.zeros((3 * k, st.n)))
        else:
            assert st.N is not None
            P_mm, P_mx = gauge_correlated(st.P, st.N, N_m, C, observer_groups(st, book, ids))
            slots = st.add_landmarks(m, P_mm, P_mx, N_p=N_m.reshape(3 * k, -1))
        book.readmit(ids)
        return slots


def observer_groups(st: JointState, book: LandmarkBook, ids: I64) -> list[tuple[I64, I64]]:
    """The landmarks `ids` by the group of vehicles their observers belong to (those linked
    by landmarks they observed, `LandmarkBook.group`): (positions in ids, the group's state
    rows) per group, what `gauge.gauge_correlated` reads each landmark's gauge error from."""
    groups = np.array([book.group(int(b)) for b in book.observers[ids]], dtype=np.int64)
    return [(np.flatnonzero(groups == g), st.vehicle_rows(int(g))) for g in np.unique(groups)]


def _anchored(
    st: JointState, run: VehicleRun, m_nav_m: F64, C: F64, N_m: F64 | None = None,
    groups: list[tuple[I64, I64]] | None = None,
) -> I64:  # fmt: skip
    """Landmarks m (k, 3) with covariances C (k, 3, 3), independent of the state, written
    relative to a new clone of run's vehicle pose: theta = f(m, a), P_tt = T_m C T_m^T +
    T_a P_aa T_a^T, P_tx = T_a P_ax; gauge rows T_m N_m + T_a N_a (N_m (k, 3, g): m's, their
    gauge error read from the vehicles of `groups`, `observer_groups`)."""
    vin = run.vin
    pose = VehiclePose.of(st, vin)
    gauge = None
    if N_m is not None and st.N is not None:  # before the clone: its columns follow below
        assert groups is not None, "a landmark put back with a gauge needs its groups"
        P_mm, P_mx = gauge_correlated(st.P, st.N, N_m, C, groups)
        gauge = P_mm, np.concatenate([P_mx, P_mx[:, pose.index] @ pose.J.T], axis=1), N_m
    key, a_rows = pose.clone(st)
    R_cb, t_bc = vin.obs.R_cam_body[0], vin.obs.t_body_cam[0]
    theta, T_m, T_a = AnchoredInverseDepth().from_nav(m_nav_m, st.x[a_rows], R_cb, t_bc)
    k = len(m_nav_m)
    F = T_a.reshape(3 * k, 6)
    P_tx = F @ st.P[a_rows, :]
    P_tt = P_tx[:, a_rows] @ F.T
    N_t = st.gauge_rows(F, a_rows)
    if gauge is None or N_t is None:
        own = T_m @ C @ np.swapaxes(T_m, 1, 2)
        for j in range(k):
            P_tt[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += own[j]
        return st.add_landmarks(theta, P_tt, P_tx, key, R_cb, t_bc, N_p=N_t)
    # with a gauge: m correlated with the state's gauge error only (gauge.gauge_correlated)
    P_mm, P_mx, N_m = gauge
    Tm = np.zeros((3 * k, 3 * k))
    for j in range(k):
        Tm[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = T_m[j]
    P_tx = P_tx + Tm @ P_mx
    cross = Tm @ P_mx[:, a_rows] @ F.T
    P_tt = P_tt + Tm @ P_mm @ Tm.T + cross + cross.T
    N_t = N_t + Tm @ N_m.reshape(3 * k, -1)
    return st.add_landmarks(theta, P_tt, P_tx, key, R_cb, t_bc, N_p=N_t)
