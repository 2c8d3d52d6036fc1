"""A vehicle in the central filter: what it brings (`VehicleInput`), what the loop keeps for
it while running (`VehicleRun`), and its pose as the joint state has it now (`VehiclePose`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.motion.models import MotionModel
from cvslam_cli.estimation.observation import StereoObservationModel
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
    copy), p_nav_m (3,), euler_rad (3,), J (6, n_v) = d(p, Psi)/d x_v, P_vv (n_v, n_v)."""

    index: I64
    x: F64
    p_nav_m: F64
    euler_rad: F64
    J: F64
    P_vv: F64

    @staticmethod
    def of(state: JointState, vin: VehicleInput) -> VehiclePose:
        index = state.vehicles[vin.name].index
        x = state.x[index]
        p, euler = vin.model.pose(x)
        return VehiclePose(
            index, x, p, euler, vin.model.pose_jacobian(x), state.P[np.ix_(index, index)]
        )

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
