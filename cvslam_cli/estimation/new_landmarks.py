"""New landmarks (type 3) and room for them in the state.

A frame's type-3 matches (`association.classify`) whose point can start a landmark become
the vehicle's candidates; a landmark is only created from a candidate that the vehicle's
next frame confirms (predicted with the new pose, inside its window, passing the descriptor
ratio test): a wrong stereo match (a random pairing) is not seen again, so it never enters
the map. When fewer than `target_tracked` landmarks were updated, up to `max_new_per_frame`
confirmed matches (spread over the image, the most precise first) are initialised with the
inverse observation model. "Most precise" is the relative depth standard deviation of the
candidate in its own (previous) frame (`new_landmark_priority: previous_frame`): the precision
of a triangulation is computed from its noisy disparity, so ranking by the precision of the
measurement that initialises the landmark (`current_frame`, the paper's way) picks the points
whose noise shortened their depth and biases the map (BENCHMARKS.md, "Fuse: consistency
(issue 15)"); the earlier frame's noise is independent of it. Each new landmark gets its
covariance and cross-covariance from the pose (standard SLAM augmentation):

    m = g(x_v, p_cam),  P_mm = G_x P_vv G_x^T + G_c C_cam G_c^T,  P_mx = G_x P_v.

In anchored inverse depth (`landmark_coordinates.py`) the same point is written relative to
an anchor clone of the vehicle's pose: a vehicle's new landmarks share its latest clone for
`anchor_span_ns` (fewer clones, a smaller state), after which the next frame that adds
landmarks clones the pose anew. By default (0) every such frame does: written in the camera
that measured it, a landmark's inverse depth is linear in its disparity and Gaussian with it;
written in an older anchor's camera it takes the measured point's skewed depth error (10 %
at 100 m with the simulated UAVs' 1.5 m baseline) into its bearing and inverse depth, which
the filter then takes for Gaussian (BENCHMARKS.md, "Fuse: the loop UAV's consistency, and
the anchor of a new landmark").

The state is kept under its landmark bound (`settings.landmark_bound`) by evicting in the
order of `mapping.LandmarkBook.eviction_order`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.association import (
    LandmarkPrediction,
    associate,
    in_view_rows,
    spread_order,
    view_rays,
)
from cvslam_cli.estimation.frame import FrameMatches
from cvslam_cli.estimation.landmark_coordinates import AnchoredInverseDepth
from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.reanchoring import hand_over
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import Candidates, VehicleInput, VehiclePose, VehicleRun
from cvslam_cli.records.arrays import F64, I64


class NewLandmarks:
    """Candidates, confirmation, initialisation and eviction (module docstring) on `state`
    and `book`, with at most `max_landmarks` in the state."""

    def __init__(
        self, state: JointState, book: LandmarkBook, settings: SlamSettings, max_landmarks: int
    ) -> None:
        self.state = state
        self.book = book
        self.settings = settings
        self.max_landmarks = max_landmarks
        # anchored coordinates: per vehicle index, the anchor its new landmarks refer to and
        # when it was cloned (a new clone once it is older than settings.anchor_span_ns)
        self._anchors: dict[int, tuple[int | None, int]] = {}

    def wanted(self, n_updated: int, target_tracked: int) -> int:
        """How many new landmarks a frame that updated `n_updated` of `target_tracked`
        should add."""
        return min(self.settings.max_new_per_frame, max(0, target_tracked - n_updated))

    def confirm(
        self, run: VehicleRun, frame: FrameMatches, free: NDArray[np.bool_]
    ) -> tuple[I64, F64]:
        """Matches of this frame (indices into it) among `free` that re-observe a candidate
        of the vehicle's previous frame (module docstring), and their priority for
        `add` (lower first: the relative depth precision, module docstring)."""
        none = np.zeros(0, dtype=np.int64), np.zeros(0)
        cand = run.candidates
        idx = np.flatnonzero(free & frame.can_start)
        if cand is None or len(cand.m) == 0 or len(idx) == 0:
            return none
        vin = run.vin
        pose = VehiclePose.of(self.state, vin)
        ok = in_view_rows(vin, pose.p_nav_m, pose.euler_rad, cand.m)
        if len(ok) == 0:
            return none
        z, _, H_m = pose.obs.predict(pose.p_nav_m, pose.euler_rad, cand.m[ok])
        R4 = np.eye(4) * self.settings.pixel_sigma_px**2
        S = H_m @ cand.cov[ok] @ np.swapaxes(H_m, 1, 2) + R4
        pred = LandmarkPrediction(ok, z, H_m, H_m, S)
        s = self.settings
        assoc = associate(
            pred, cand.desc[ok], frame.z[idx], frame.desc[idx], s.gate_chi2, s.descriptor_ratio,
            s.max_descriptor_distance,
        )  # fmt: skip
        rows = idx[assoc.match_index]
        if s.new_landmark_priority == "current_frame":
            return rows, frame.depth_sigma_ratio[rows]
        return rows, cand.depth_sigma_ratio[ok[assoc.pred_index]]

    def remember_candidates(
        self, run: VehicleRun, frame: FrameMatches, free: NDArray[np.bool_]
    ) -> None:
        """This frame's free matches become the candidates the next frame may confirm."""
        idx = np.flatnonzero(free & frame.can_start)
        vin = run.vin
        pose = VehiclePose.of(self.state, vin)
        p_cam, cov_cam, _ = frame.camera_points(idx, pose.right_cx_px)
        m, cov = vin.obs.landmark_from_camera_point(
            pose.p_nav_m, pose.euler_rad, p_cam, cov_cam, pose.cov
        )
        run.candidates = Candidates(
            m, cov, frame.desc[idx], frame.z[idx], frame.depth_sigma_ratio[idx], frame.stamp_ns
        )

    def add(
        self,
        run: VehicleRun,
        runs: list[VehicleRun],
        frame: FrameMatches,
        cand: I64,
        priority: F64,
        protected: I64,
        want: int,
    ) -> tuple[I64, I64]:
        """Initialise up to `want` of the matches `cand` (confirmed candidates) as landmarks,
        evicting landmarks (never `protected`) when the state is full; `runs`: every
        vehicle's, in vehicle order. Returns their slots and the frame rows they came from."""
        size = tuple(run.vin.features.rig.size_px[0])
        pick = cand[spread_order(frame.z[cand, :2], priority, size)[:want]]
        pick = self.make_room(run, runs, protected, pick)
        if len(pick) == 0:
            return np.zeros(0, dtype=np.int64), pick
        vin = run.vin
        pose = VehiclePose.of(self.state, vin)
        p_cam, cov_cam, dp_du = frame.camera_points(pick, pose.right_cx_px)
        if self.state.coords.anchored:
            key, since_ns = self._anchors.get(run.index, (None, frame.stamp_ns))
            if frame.stamp_ns - since_ns > self.settings.anchor_span_ns:
                key, since_ns = None, frame.stamp_ns
            slots, new_key = _anchored(self.state, vin, pose, p_cam, cov_cam, key, dp_du)
            self._anchors[run.index] = (new_key, since_ns if new_key == key else frame.stamp_ns)
            if new_key != key:  # a new clone: the lightest anchors hand theirs over to it
                hand_over(
                    self.state, new_key, vin.obs.R_cam_body[0], vin.obs.t_body_cam[0],
                    vin.obs.K[0], tuple(vin.features.rig.size_px[0]),
                    self.settings.reanchor_max_landmarks,
                )  # fmt: skip
        else:
            slots = _cartesian(self.state, vin, pose, p_cam, cov_cam, dp_du)
        ids = self.book.add(
            frame.desc[pick],
            run.index,
            frame.stamp_ns,
            frame.true_id[pick],
            *view_rays(vin, pose.p_nav_m, pose.euler_rad, self.state.landmarks(slots)),
        )
        run.observations.add(frame.stamp_ns, ids, frame.z[pick])
        return slots, pick

    def make_room(self, run: VehicleRun, runs: list[VehicleRun], protected: I64, pick: I64) -> I64:
        """Evict landmarks (in batches of at least a tenth of the bound: fewer copies) when
        `pick` would not fit; returns the part of `pick` that fits."""
        st = self.state
        bound = self.max_landmarks
        over = st.n_landmarks + len(pick) - bound
        if over <= 0:
            return pick
        covs = st.landmark_covariances(np.arange(st.n_landmarks))
        # each other vehicle's latest frame: the landmarks it is tracking go last
        latest = np.array(
            [r.stamps_ns[-1] if r.stamps_ns and r is not run else NEVER for r in runs],
            dtype=np.int64,
        )
        order = self.book.eviction_order(
            protected, np.trace(covs, axis1=1, axis2=2), latest, self.settings.others_tracking_ns
        )
        evict = order[: max(over, bound // 10)]
        self.book.evict(
            evict, st.landmarks(evict), covs[evict], run.t_ns, st.landmark_gauge(evict)
        )  # fmt: skip
        self.book.keep_slots(st.remove_landmarks(evict))
        return pick[: max(0, bound - st.n_landmarks)]


def _cartesian(
    st: JointState,
    vin: VehicleInput,
    pose: VehiclePose,
    p_cam_m: F64,
    cov_cam_m2: F64,
    dp_cam_du: F64 | None = None,
) -> I64:
    """Cartesian landmarks from points p_cam_m (k, 3) in the left camera with covariances
    cov_cam_m2 (k, 3, 3) (module docstring: m = g(x_v, p_cam)); dp_cam_du (k, 3): how the
    points move with the vehicle's estimate of its rig's right principal point (None: they
    do not; `VehiclePose.point_jacobian`)."""
    m, J_pose, J_pc = vin.obs.landmark_jacobians(pose.p_nav_m, pose.euler_rad, p_cam_m)
    k = len(m)
    Jx = pose.point_jacobian(J_pose, J_pc, dp_cam_du).reshape(3 * k, len(pose.index))
    P_mx = Jx @ st.P[pose.index, :]
    P_mm = P_mx[:, pose.index] @ Jx.T
    _add_diagonal_blocks(P_mm, J_pc @ cov_cam_m2 @ J_pc.T)
    return st.add_landmarks(m, P_mm, P_mx, N_p=st.gauge_rows(Jx, pose.index))


def _anchored(
    st: JointState,
    vin: VehicleInput,
    pose: VehiclePose,
    p_cam_m: F64,
    cov_cam_m2: F64,
    anchor_key: int | None,
    dp_cam_du: F64 | None = None,
) -> tuple[I64, int]:
    """Anchored inverse-depth landmarks (`landmark_coordinates.py`) from the same points,
    relative to the anchor `anchor_key` (None, or one no longer in the state: a new clone of
    the pose (p, Psi) = J x_v, P_aa = J P_vv J^T, P_ax = J P_v). theta = f(x_v, x_a, p_cam)
    through the Cartesian point, augmented like it (P_tx = F P_(v,a),x, P_tt = F P F^T +
    F_c C_cam F_c^T); from a fresh clone theta depends on p_cam only (and on the rig's
    right principal point through it, `dp_cam_du`, as in `_cartesian`). Returns the slots
    and the anchor's key."""
    a_rows = None if anchor_key is None else st.anchor_rows(anchor_key)
    if anchor_key is None or a_rows is None:
        anchor_key, a_rows = pose.clone(st)
    R_cb, t_bc = vin.obs.R_cam_body[0], vin.obs.t_body_cam[0]
    m, J_pose, J_pc = vin.obs.landmark_jacobians(pose.p_nav_m, pose.euler_rad, p_cam_m)
    theta, T_m, T_a = AnchoredInverseDepth().from_nav(m, st.x[a_rows], R_cb, t_bc)
    k = len(m)
    F_c = T_m @ J_pc  # d theta / d p_cam
    F = np.concatenate(
        [
            pose.point_jacobian(T_m @ J_pose, F_c, dp_cam_du).reshape(3 * k, len(pose.index)),
            T_a.reshape(3 * k, 6),
        ],
        axis=1,
    )
    rows = np.concatenate([pose.index, a_rows])
    P_tx = F @ st.P[rows, :]
    P_tt = P_tx[:, rows] @ F.T
    _add_diagonal_blocks(P_tt, F_c @ cov_cam_m2 @ np.swapaxes(F_c, 1, 2))
    N_t = st.gauge_rows(F, rows)
    return st.add_landmarks(theta, P_tt, P_tx, anchor_key, R_cb, t_bc, N_p=N_t), anchor_key


def _add_diagonal_blocks(P: F64, blocks: F64) -> None:
    """P (3k, 3k) += block-diagonal of blocks (k, 3, 3), in place: the measurement's part of
    the new landmarks' covariance."""
    for j, block in enumerate(blocks):
        P[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += block
