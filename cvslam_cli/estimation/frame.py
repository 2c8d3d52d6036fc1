"""One stereo frame of one vehicle as the filter's loop sees it: its matches, read from the
feature set once (`FrameMatches`), and what the frame did (`FrameOutcome`, the timeline
row's counts), filled in by the loop's steps."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.observation import RightCxShift
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet


@dataclass(frozen=True, eq=False)
class FrameMatches:
    """The M stereo matches of frame `index` of a vehicle, taken at `stamp_ns`:
    z (M, 4) observations (u_l, v_l, u_r, v_r), undistorted pixels (eq. 19's measurement);
    desc (M, 128) left-image descriptors; p_cam_m (M, 3) triangulated points in the left
    camera frame with covariances cov_cam_m2 (M, 3, 3) (the inverse observation model);
    true_id (M,) the simulator's landmark ids (-1 unknown); depth_sigma_ratio (M,) the depth
    standard deviation of each point over its depth; can_start (M,) whether a match's point
    can start a landmark (finite, in front, depth_sigma_ratio below the configured bound);
    octave (M,) the left keypoint's SIFT octave (0: the image's own resolution);
    dp_cam_du (M, 3) d p_cam / d du where the vehicle's rig's right principal point is
    corrected or estimated by du (`rig_calibration.py`; the points then moved to it by
    `shift`), else None."""

    stamp_ns: int
    index: int
    z: F64
    desc: NDArray[np.uint8]
    p_cam_m: F64
    cov_cam_m2: F64
    true_id: I64
    depth_sigma_ratio: F64
    can_start: NDArray[np.bool_]
    octave: I64
    dp_cam_du: F64 | None = None
    shift: RightCxShift | None = None

    @staticmethod
    def of(
        fs: FeatureSet,
        index: int,
        stamp_ns: int,
        max_depth_sigma_ratio: float,
        shift: RightCxShift | None = None,
    ) -> FrameMatches:
        """Frame `index` of `fs`; with `shift`, its points moved to the rig's corrected or
        estimated right principal point (`observation.RightCxShift`)."""
        sl = fs.frame_matches(index)
        ml, mr = fs.match_left[sl], fs.match_right[sl]
        p_cam = fs.match_p_cam_m[sl]
        cov_cam = fs.match_cov_cam_m2[sl]
        dp_cam_du = None
        if shift is not None:
            p_cam, cov_cam, dp_cam_du = shift.apply(p_cam, cov_cam)
        depth = p_cam[:, 2]
        sigma = np.sqrt(np.maximum(cov_cam[:, 2, 2], 0.0))
        with np.errstate(invalid="ignore", divide="ignore"):
            can_start = np.isfinite(depth) & (depth > 0) & (sigma < max_depth_sigma_ratio * depth)
            depth_sigma_ratio = sigma / depth
        return FrameMatches(
            stamp_ns=stamp_ns,
            index=index,
            z=np.concatenate([fs.left_uv_px[ml], fs.right_uv_px[mr]], axis=1).astype(float),
            desc=fs.left_desc[ml],
            p_cam_m=p_cam,
            cov_cam_m2=cov_cam,
            true_id=fs.match_landmark_id[sl],
            depth_sigma_ratio=depth_sigma_ratio,
            can_start=can_start,
            octave=fs.left_octave[ml].astype(np.int64),
            dp_cam_du=dp_cam_du,
            shift=shift,
        )

    def __len__(self) -> int:
        return len(self.z)

    def camera_points(self, rows: I64, du_px: float) -> tuple[F64, F64, F64 | None]:
        """The stereo points of matches `rows` (p_cam (k, 3), cov (k, 3, 3), dp_cam_du or
        None) moved to the rig's right principal point corrected by du_px, from where they
        were read (`shift`): a vehicle that estimates it has updated it since. The moves
        compose: d + du1 + (du2 - du1) = d + du2."""
        p, cov = self.p_cam_m[rows], self.cov_cam_m2[rows]
        if self.shift is None or self.dp_cam_du is None:
            return p, cov, None
        if du_px == self.shift.du_px:
            return p, cov, self.dp_cam_du[rows]
        return RightCxShift(self.shift.fx_baseline, du_px - self.shift.du_px).apply(p, cov)


@dataclass(frozen=True)
class WindowOutcome:
    """One frame's sliding-window step: tracks continued / ended and used / gated out, and
    the update's NIS and degrees of freedom (nan / 0 without an update)."""

    continued: int = 0
    used: int = 0
    rejected: int = 0
    nis: float = float("nan")
    dof: int = 0


@dataclass(eq=False)
class FrameOutcome:
    """What one frame did. types (M,): each match's feature type (`association.classify`;
    0 until classified); updated_slots: the landmarks it updated; the counts of the timeline
    row; nis / dof of its update and the gamma used."""

    types: NDArray[np.int8]
    updated_slots: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    visible: int = 0
    type1: int = 0
    type2: int = 0
    type3: int = 0
    loop: int = 0
    reactivated: int = 0
    rejected: int = 0
    nis: float = float("nan")
    dof: int = 0
    gamma: float = float("nan")
    gamma_raised: bool = False
    linearisations: int = 0
    lost: bool = False  # the vehicle was lost at this frame (relocalisation.py)
    new_rows: I64 = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    window: WindowOutcome = field(default_factory=WindowOutcome)
