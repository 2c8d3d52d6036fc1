"""The arrays a refinement starts from and ends with (no I/O, no GTSAM)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cvslam_cli.estimation.motion.models import MotionModel
from cvslam_cli.records.arrays import F64, I64, check_shape

RobustKernel = Literal["huber", "cauchy", "none"]
Ordering = Literal["metis", "colamd"]


@dataclass(frozen=True, eq=False)
class RefineVehicle:
    """One vehicle's keyframes and motion data.

    stamps_ns (K,) keyframe stamps, increasing; T_nav_body (K, 4, 4) the initial poses (the
    filter's estimate); `model` the filter's motion model (its kind picks the motion factor,
    its noise densities weight it); x_first (n,), P_first (n, n) the filter's prior state at
    the first keyframe (its initial state predicted to that stamp: the gauge);
    motion_stamps_ns (M,) / motion_inputs (M, d) the IMU or odometry samples (M = 0 for
    the constant-velocity model); K_px (2, 3, 3) left/right intrinsics (undistorted pixels),
    T_body_cam (2, 4, 4) left/right camera (optical) to body (FRD)."""

    name: str
    model: MotionModel
    stamps_ns: I64
    T_nav_body: F64
    x_first: F64
    P_first: F64
    motion_stamps_ns: I64
    motion_inputs: F64
    K_px: F64
    T_body_cam: F64

    def __post_init__(self) -> None:
        dims: dict[str, int] = {"n": self.model.n}
        check_shape(f"{self.name}: stamps_ns", self.stamps_ns, ("K",), "iu", dims)
        check_shape(f"{self.name}: T_nav_body", self.T_nav_body, ("K", 4, 4), "f", dims)
        check_shape(f"{self.name}: x_first", self.x_first, ("n",), "f", dims)
        check_shape(f"{self.name}: P_first", self.P_first, ("n", "n"), "f", dims)
        check_shape(f"{self.name}: motion_stamps_ns", self.motion_stamps_ns, ("M",), "iu", dims)
        check_shape(f"{self.name}: K_px", self.K_px, (2, 3, 3), "f", dims)
        check_shape(f"{self.name}: T_body_cam", self.T_body_cam, (2, 4, 4), "f", dims)
        if len(self.stamps_ns) > 1 and np.any(np.diff(self.stamps_ns) <= 0):
            raise ValueError(f"{self.name}: keyframe stamps must increase")


@dataclass(frozen=True, eq=False)
class RefineProblem:
    """Vehicles and N observations of L landmarks: obs_vehicle (N,) index into `vehicles`,
    obs_keyframe (N,) index into that vehicle's keyframes, obs_landmark (N,) index into
    landmark_id (L,) / p_nav_m (L, 3) (initial positions, nav frame), z_px (N, 4)
    (u_l, v_l, u_r, v_r)."""

    vehicles: tuple[RefineVehicle, ...]
    obs_vehicle: I64
    obs_keyframe: I64
    obs_landmark: I64
    z_px: F64
    landmark_id: I64
    p_nav_m: F64

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        for name in ("obs_vehicle", "obs_keyframe", "obs_landmark"):
            check_shape(f"RefineProblem.{name}", getattr(self, name), ("N",), "iu", dims)
        check_shape("RefineProblem.z_px", self.z_px, ("N", 4), "f", dims)
        check_shape("RefineProblem.landmark_id", self.landmark_id, ("L",), "iu", dims)
        check_shape("RefineProblem.p_nav_m", self.p_nav_m, ("L", 3), "f", dims)


@dataclass(frozen=True)
class RefineSettings:
    """pixel_sigma_px: standard deviation of each pixel coordinate; robust kernel and its
    threshold robust_k (in standard deviations of the whitened residual); planar_sigma: the
    standard deviation (m, rad) holding a ground robot's height, roll and pitch (its 3-DOF
    model fixes them); LM's iteration limit and relative error decrease to stop at, and
    the elimination ordering of its linear solves (METIS's nested dissection or COLAMD);
    landmark_covariances: also the landmarks' marginal covariances (map std columns);
    estimate_right_cx: also correct each rig's right-camera principal point u0 (px, prior
    N(0, right_cx_sigma_px^2); `right_cx.py`)."""

    pixel_sigma_px: float = 0.5
    robust: RobustKernel = "huber"
    robust_k: float = 1.345
    planar_sigma: float = 1e-3
    max_iterations: int = 50
    relative_error_tol: float = 1e-6
    ordering: Ordering = "metis"
    landmark_covariances: bool = True
    estimate_right_cx: bool = False
    right_cx_sigma_px: float = 1.0


@dataclass(frozen=True, eq=False)
class RefinedVehicle:
    """stamps_ns (K,), T_nav_body (K, 4, 4), pose_cov (K, 6, 6): marginal covariance of
    (x, y, z [m] nav, roll, pitch, yaw [rad]) (as the fuse stage's pose covariances; zero
    rows and columns for the states a ground robot's model does not have)."""

    name: str
    stamps_ns: I64
    T_nav_body: F64
    pose_cov: F64


@dataclass(frozen=True, eq=False)
class RefineResult:
    """Refined vehicles; the landmarks' refined positions p_nav_m (L, 3) (problem order) and
    marginal covariances cov (L, 3, 3) (NaN when not computed); the graph's error before and
    after, iterations, factor counts by kind; outlier observations (whitened residual above
    the robust threshold at the solution)."""

    vehicles: tuple[RefinedVehicle, ...]
    p_nav_m: F64
    cov: F64
    initial_error: float
    final_error: float
    iterations: int
    factors: dict[str, int]
    outliers: int
