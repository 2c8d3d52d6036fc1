"""A vehicle block that also estimates its stereo rig's right principal point: the
calibration pass of `rig_calibration.py` (`fuse.calibration.estimate_right_cx`).

A rectified stereo rig whose right camera's principal point u0 (cx) is off along x by du
pixels measures every disparity short by du: a point's depth fx b / d is too long by a
factor (d + du) / d, far points most (KITTI clip b's "4-5 % scale disagreement" is such an
offset of ~0.9 px, clip a's ~0.2 px; BENCHMARKS.md "Refine: the right camera's principal
point"). `cvslam refine` estimates du in its batch solution; this block lets the filter
estimate it, as a state of the vehicle (OpenVINS estimates its cameras' intrinsics the
same way):

    x = [x_motion (n_m), du (px)],   du' = du (a constant of the log: F = 1, no noise)

The observation model predicts the right pixel at u_r + du (d u_r / d du = 1), and a stereo
point triangulated with the calibrated rig is moved to the disparity d + du before it starts
a landmark, whose covariance then carries its correlation with du (`observation.RightCxShift`,
`vehicle.VehiclePose`).
The motion model's states keep their rows, so everything that reads the block by its state
names (the pose, the gauge, relocalisation's forgotten rows) reads it unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.estimation.motion.models import InitialUncertainty, MotionModel
from cvslam_cli.records.arrays import F64

RIGHT_CX_STATE = "du0_right_px"


@dataclass(frozen=True)
class RightCxCalibrated:
    """`motion`'s block followed by du (px), the right camera's principal point correction,
    with prior standard deviation `sigma_px` (its estimate starts at 0: the calibration)."""

    motion: MotionModel
    sigma_px: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma_px) and self.sigma_px > 0):
            raise ValueError(f"right cx prior sigma: expected a number > 0, got {self.sigma_px!r}")

    @property
    def kind(self) -> str:
        return self.motion.kind

    @property
    def n(self) -> int:
        return self.motion.n + 1

    @property
    def input_size(self) -> int:
        return self.motion.input_size

    @property
    def state_names(self) -> tuple[str, ...]:
        return (*self.motion.state_names, RIGHT_CX_STATE)

    @property
    def right_cx_row(self) -> int:
        """du's row in the block."""
        return self.motion.n

    def step(self, x: F64, u: F64, dt: float) -> tuple[F64, F64, F64]:
        x_m, F_m, Q_m = self.motion.step(x[:-1], u, dt)
        n = self.n
        F = np.zeros((n, n))
        F[:-1, :-1] = F_m
        F[-1, -1] = 1.0
        Q = np.zeros((n, n))
        Q[:-1, :-1] = Q_m
        return np.append(x_m, x[-1]), F, Q

    def pose(self, x: F64) -> tuple[F64, F64]:
        return self.motion.pose(x[:-1])

    def pose_jacobian(self, x: F64) -> F64:
        return np.pad(self.motion.pose_jacobian(x[:-1]), ((0, 0), (0, 1)))

    def initial_state(self, p_nav_m: F64, euler_rad: F64, v_nav_m_s: F64, w_body_rad_s: F64) -> F64:
        x = self.motion.initial_state(p_nav_m, euler_rad, v_nav_m_s, w_body_rad_s)
        return self.extend_state(x)

    def initial_covariance(self, init: InitialUncertainty) -> F64:
        return self.extend_covariance(self.motion.initial_covariance(init))

    def with_pose(self, x: F64, p_nav_m: F64, euler_rad: F64) -> F64:
        return np.append(self.motion.with_pose(x[:-1], p_nav_m, euler_rad), x[-1])

    def extend_state(self, x_motion: F64) -> F64:
        """(n,) a motion state x_motion (n_m,) with du = 0 appended."""
        return np.append(np.asarray(x_motion, dtype=float), 0.0)

    def extend_covariance(self, P_motion: F64) -> F64:
        """(n, n) a motion covariance with du's prior variance appended (uncorrelated)."""
        n = self.n
        P = np.zeros((n, n))
        P[:-1, :-1] = P_motion
        P[-1, -1] = self.sigma_px**2
        return P


def right_cx_row(model: MotionModel) -> int | None:
    """The row of du in a vehicle block of `model` (None: the rig is not calibrated)."""
    return model.right_cx_row if isinstance(model, RightCxCalibrated) else None
