"""Camera models and the stereo rig.

A `CameraModel` holds what `sensor_msgs/msg/CameraInfo` holds (K, D, R, P, size) plus the
camera's mounting `T_body_cam` (camera optical frame x right, y down, z forward -> body).
A `StereoRig` pairs two of them and derives the baseline; `validate` rejects what no later
stage could use (non-positive focal length, zero baseline, image size disagreeing with K).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cvslam_cli.errors import CalibrationError
from cvslam_cli.geometry.rotations import invert_T, is_rotation, make_T
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.features import RigCalibration

DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant", "none")
# How many coefficients each model takes (OpenCV's accepted lengths; ROS writes 5, 8 and 4).
DISTORTION_COEFFICIENTS = {
    "plumb_bob": (4, 5),
    "rational_polynomial": (8, 12, 14),
    "equidistant": (4,),
}


@dataclass(frozen=True, eq=False)
class CameraModel:
    """One calibrated camera.

    K: (3, 3) intrinsics. D: (n,) distortion coefficients of `distortion_model`
    (plumb_bob: k1 k2 p1 p2 k3). R_rect: (3, 3) rectification rotation. P: (3, 4) projection
    matrix of the rectified camera (for the right camera of a rectified pair P[0, 3] = -fx * b).
    T_body_cam: (4, 4). `source` says where the calibration came from (e.g. "camera_info",
    "config", "euroc sensor.yaml").
    """

    width: int
    height: int
    K: F64
    D: F64 = field(default_factory=lambda: np.zeros(0))
    distortion_model: str = "none"
    R_rect: F64 = field(default_factory=lambda: np.eye(3))
    P: F64 | None = None
    T_body_cam: F64 = field(default_factory=lambda: np.eye(4))
    frame_id: str = ""
    source: str = "config"

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def has_distortion(self) -> bool:
        return bool(self.D.size and np.any(self.D != 0))

    def validate(self, name: str) -> None:
        """Raise `CalibrationError` naming `name` (e.g. the CameraInfo topic) if unusable."""
        K = np.asarray(self.K)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CalibrationError(f"{name}: intrinsics K must be a finite 3x3 matrix")
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(
                f"{name}: non-positive focal length (fx={self.fx:g}, fy={self.fy:g})"
            )
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"{name}: image size {self.width}x{self.height} is not positive")
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise CalibrationError(
                f"{name}: principal point ({self.cx:g}, {self.cy:g}) lies "
                f"outside the {self.width}x{self.height} image"
            )
        if self.distortion_model not in DISTORTION_MODELS:
            raise CalibrationError(
                f"{name}: unknown distortion model "
                f"{self.distortion_model!r} (expected one of "
                f"{', '.join(DISTORTION_MODELS)})"
            )
        counts = DISTORTION_COEFFICIENTS.get(self.distortion_model)
        if counts is not None and np.asarray(self.D).size not in counts:
            raise CalibrationError(
                f"{name}: {self.distortion_model} distortion takes "
                f"{' or '.join(map(str, counts))} coefficients, got {np.asarray(self.D).size}"
            )
        if self.distortion_model == "none" and np.any(np.asarray(self.D) != 0):
            raise CalibrationError(f"{name}: distortion model 'none' with non-zero coefficients")
        if not np.all(np.isfinite(self.D)):
            raise CalibrationError(f"{name}: distortion coefficients are not finite")
        if not is_rotation(self.T_body_cam[:3, :3], tol=1e-4):
            raise CalibrationError(f"{name}: T_body_cam is not a rigid transform")
        if self.P is not None and (self.P.shape != (3, 4) or not np.all(np.isfinite(self.P))):
            raise CalibrationError(f"{name}: projection matrix P must be a finite 3x4 matrix")

    def check_image_size(self, width: int, height: int, name: str) -> None:
        if (width, height) != (self.width, self.height):
            raise CalibrationError(
                f"{name}: image is {width}x{height} but its calibration "
                f"({self.source}) is for {self.width}x{self.height}"
            )

    def describe(self) -> dict[str, object]:
        return {
            "source": self.source,
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "distortion_model": self.distortion_model,
            "D": [float(d) for d in self.D],
            "frame_id": self.frame_id,
        }


@dataclass(frozen=True, eq=False)
class StereoRig:
    """Left and right camera of one vehicle; `T_left_right` maps right-camera coordinates to
    left-camera coordinates."""

    left: CameraModel
    right: CameraModel

    @property
    def T_left_right(self) -> F64:
        return invert_T(self.left.T_body_cam) @ self.right.T_body_cam

    @property
    def baseline_from_projection_m(self) -> float | None:
        """Baseline b from the rectified right projection matrix (P[0, 3] = -fx * b)."""
        P = self.right.P
        if P is None or P[0, 3] == 0 or P[0, 0] == 0:
            return None
        return float(-P[0, 3] / P[0, 0])

    @property
    def baseline_m(self) -> float:
        """Distance between the optical centres, from the extrinsics."""
        return float(np.linalg.norm(self.T_left_right[:3, 3]))

    @property
    def rectified(self) -> bool:
        """No distortion, identical orientation, right camera displaced along x only."""
        T = self.T_left_right
        t = T[:3, 3]
        return bool(
            not self.left.has_distortion
            and not self.right.has_distortion
            and np.allclose(T[:3, :3], np.eye(3), atol=1e-6)
            and abs(t[1]) + abs(t[2]) <= 1e-6 * max(abs(t[0]), 1e-9)
        )

    def validate(self, name: str) -> None:
        self.left.validate(f"{name} left camera")
        self.right.validate(f"{name} right camera")
        if self.baseline_m < 1e-6:
            raise CalibrationError(
                f"{name}: zero stereo baseline (left and right cameras are at the same place)"
            )
        b_p = self.baseline_from_projection_m
        if b_p is not None and b_p <= 0:
            raise CalibrationError(
                f"{name}: right projection matrix gives a non-positive baseline ({b_p:g} m)"
            )

    def describe(self) -> dict[str, object]:
        return {
            "left": self.left.describe(),
            "right": self.right.describe(),
            "baseline_m": self.baseline_m,
            "rectified": self.rectified,
            "T_left_right": self.T_left_right.round(9).tolist(),
        }


def translation_T(x: float, y: float = 0.0, z: float = 0.0) -> F64:
    return make_T(np.eye(3), np.array([x, y, z]))


def rig_calibration(rig: StereoRig) -> RigCalibration:
    """The `RigCalibration` record of a stereo rig."""
    D = np.zeros((2, 5))
    for i, cam in enumerate((rig.left, rig.right)):
        d = np.asarray(cam.D, dtype=float)[:5]
        D[i, : d.size] = d
    return RigCalibration(
        K=np.stack([rig.left.K, rig.right.K]).astype(float),
        D=D,
        distortion_model=rig.left.distortion_model,
        T_body_cam=np.stack([rig.left.T_body_cam, rig.right.T_body_cam]).astype(float),
        size_px=np.array(
            [[rig.left.width, rig.left.height], [rig.right.width, rig.right.height]], dtype=np.int64
        ),
    )


def stereo_rig(calib: RigCalibration) -> StereoRig:
    """The `StereoRig` of a stored calibration (inverse of `rig_calibration`)."""
    cams = [
        CameraModel(
            width=int(calib.size_px[i, 0]),
            height=int(calib.size_px[i, 1]),
            K=calib.K[i],
            D=calib.D[i],
            distortion_model=calib.distortion_model,
            T_body_cam=calib.T_body_cam[i],
            source="feature file",
        )
        for i in range(2)
    ]
    return StereoRig(cams[0], cams[1])
