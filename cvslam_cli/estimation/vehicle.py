"""A vehicle in the central filter: what it brings (`VehicleInput`), what the loop keeps for
it while running (`VehicleRun`), and its pose as the joint state has it now (`VehiclePose`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.motion.calibration import RightCxCalibrated, right_cx_row
from cvslam_cli.estimation.motion.models import MotionModel
from cvslam_cli.estimation.observation import RightCxShift, StereoObservationModel
from cvslam_cli.estimation.observation_log import ObservationLog
from cvslam_cli.estimation.state import JointState
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet


@dataclass(frozen=True, eq=False)
class VehicleInput:
    """One vehicle: its motion model, initial state x0 (n,) / P0 (n, n) at `start_ns`,
    motion samples `motion_stamps_ns` (K,) with inputs (K, input_size) (empty for the
    constant-velocity model), its features and stereo observation model. `pose_known` False:
    x0 is only a rough prior; the vehicle is localised in the shared map first
    (`unknown_pose.py`) and neither updates nor maps until then."""

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
    right_cx_px: float = 0.0

    def with_right_cx(self, du_px: float) -> VehicleInput:
        """This vehicle with its rig's right principal point u0 corrected by du_px (a known or
        estimated correction, `rig_calibration.py`): `obs` predicts with it, and the stereo
        points of its frames are moved to it as they are read (`right_cx_px`, the correction
        relative to the feature file's rig, `observation.RightCxShift`)."""
        return replace(
            self, obs=self.obs.with_right_cx(du_px), right_cx_px=self.right_cx_px + du_px
        )

    def with_right_cx_state(self, sigma_px: float) -> VehicleInput:
        """This vehicle with a further correction of its rig's right principal point a state
        of its block, of prior standard deviation sigma_px (`motion/calibration.py`)."""
        if not self.obs.rectified:
            raise ValueError(f"vehicle {self.name}: the right principal point of a rig that is "
                             "not rectified cannot be estimated")  # fmt: skip
        model = RightCxCalibrated(self.model, sigma_px)
        return replace(
            self, model=model, x0=model.extend_state(self.x0), P0=model.extend_covariance(self.P0)
        )


@dataclass(frozen=True, eq=False)
class Candidates:
    """A vehicle's unmatched stereo points of its last frame (k), which its next frame may
    confirm as new landmarks (type 3) and another vehicle's new landmarks may be jointly
    initialised with: nav positions m (k, 3) with covariances cov (k, 3, 3) from its pose
    then, descriptors desc (k, 128), the observations z (k, 4), depth_sigma_ratio (k,) the
    relative depth standard deviation of each point's triangulation, and the frame's stamp."""

    m: F64
    cov: F64
    desc: NDArray[np.uint8]
    z: F64
    depth_sigma_ratio: F64
    stamp_ns: int

    def without(self, rows: I64) -> Candidates:
        keep = np.ones(len(self.m), dtype=bool)
        keep[rows] = False
        return Candidates(
            self.m[keep], self.cov[keep], self.desc[keep], self.z[keep],
            self.depth_sigma_ratio[keep], self.stamp_ns,
        )  # fmt: skip


@dataclass(eq=False)
class VehicleRun:
    """Per-vehicle bookkeeping during a run: `index` (its bit in the landmark book), the time
    its state was predicted to (`t_ns`), the estimates recorded at its frames (`stamps_ns`, vehicle
    states x (n,), pose covariances (6, 6)), when its pose became known (its start, or when
    it was localised; None while unknown), when the map by appearance last confirmed it
    (`verified_ns`: its start or localisation, or a check that agreed) and when it last
    tracked the map (`tracked_ns`), when it was last lost and how often
    (`relocalisation.py`), its last frame's candidates and the observations it made
    (`observation_log.py`)."""

    vin: VehicleInput
    index: int
    t_ns: int
    localised_ns: int | None
    stamps_ns: list[int] = field(default_factory=list)
    x: list[F64] = field(default_factory=list)
    pose_cov: list[F64] = field(default_factory=list)
    candidates: Candidates | None = None
    observations: ObservationLog = field(default_factory=ObservationLog)  # for refine
    verified_ns: int | None = None
    tracked_ns: int | None = None
    lost_ns: int | None = None
    losses: int = 0

    @staticmethod
    def start(vin: VehicleInput, index: int) -> VehicleRun:
        known = vin.start_ns if vin.pose_known else None
        return VehicleRun(vin, index, vin.start_ns, known, verified_ns=known, tracked_ns=known)

    @property
    def localised(self) -> bool:
        return self.localised_ns is not None

    def localise(self, t_ns: int) -> None:
        """Its pose is known from t_ns (found in the map)."""
        self.localised_ns = t_ns
        self.verified_ns = self.tracked_ns = t_ns

    def lose(self, t_ns: int) -> None:
        """Its pose is unknown from t_ns (the map contradicts it: `relocalisation.py`)."""
        self.localised_ns = None
        self.lost_ns = t_ns
        self.losses += 1


@dataclass(frozen=True, eq=False)
class VehiclePose:
    """A vehicle's block of the joint state now: `index` (n_v,) its state rows, x (n_v,) (a
    copy), p_nav_m (3,), euler_rad (3,), J (6, n_v) = d(p, Psi)/d x_v, P_vv (n_v, n_v); `obs`
    its stereo observation model with the rig's right principal point as corrected
    (`VehicleInput.right_cx_px`) and as the block estimates it, where it does
    (`right_cx_row`, `motion/calibration.py`; else None); `right_cx_px` the two together."""

    index: I64
    x: F64
    p_nav_m: F64
    euler_rad: F64
    J: F64
    P_vv: F64
    obs: StereoObservationModel
    right_cx_row: int | None = None
    right_cx_px: float = 0.0

    @staticmethod
    def of(state: JointState, vin: VehicleInput) -> VehiclePose:
        index = state.vehicles[vin.name].index
        x = state.x[index]
        p, euler = vin.model.pose(x)
        row = right_cx_row(vin.model)
        du = 0.0 if row is None else float(x[row])
        return VehiclePose(
            index, x, p, euler, vin.model.pose_jacobian(x), state.P[np.ix_(index, index)],
            vin.obs.with_right_cx(du), row, vin.right_cx_px + du,
        )  # fmt: skip

    def vehicle_jacobian(self, H_pose: F64) -> F64:
        """(N, 4, n_v) d z / d x_v of observations (u_l, v_l, u_r, v_r) whose Jacobian w.r.t.
        (p, Psi) is H_pose (N, 4, 6): H_pose J, and d u_r / d du = 1 where the block holds
        du."""
        H_v = H_pose @ self.J
        if self.right_cx_row is not None:
            H_v[:, 2, self.right_cx_row] += 1.0
        return H_v

    def point_jacobian(self, J_pose: F64, J_pc: F64, dp_cam_du: F64 | None) -> F64:
        """(k, d, n_v) d m / d x_v of k points m = g(p, Psi, p_cam) of d numbers whose
        Jacobians w.r.t. (p, Psi) and the camera point are J_pose (k, d, 6) and J_pc ((k,) d,
        3) (`landmark_jacobians`), the camera points moving with du by dp_cam_du (k, 3)
        (`observation.RightCxShift`; None: they do not)."""
        J_x = J_pose @ self.J
        if self.right_cx_row is not None and dp_cam_du is not None:
            J_x[:, :, self.right_cx_row] += (J_pc @ dp_cam_du[:, :, None])[:, :, 0]
        return J_x

    def right_cx_shift(self) -> RightCxShift | None:
        """How this vehicle's stereo points move from the feature file's rig to the one it
        observes with (None: the same rig)."""
        if self.right_cx_row is None and self.right_cx_px == 0.0:
            return None
        return RightCxShift(self.obs.fx_baseline, self.right_cx_px)

    @property
    def cov(self) -> F64:
        """(6, 6) covariance of (p, Psi)."""
        return self.J @ self.P_vv @ self.J.T

    def clone(self, state: JointState, pinned: bool = False) -> tuple[int, I64]:
        """A clone of this pose (p, Psi) = J x_v added to `state` as an anchor, with its
        covariance J P_vv J^T and cross-covariance J P_v,: with the state; (its key, its 6
        state rows). `pinned`: kept until released even while no landmark refers to it."""
        P_ax = self.J @ state.P[self.index, :]
        return state.add_anchor(
            np.concatenate([self.p_nav_m, self.euler_rad]), P_ax[:, self.index] @ self.J.T,
            P_ax, pinned, N_a=state.gauge_rows(self.J, self.index),
        )  # fmt: skip
