"""The stereo rigs of the matcher tests: 752x480 pinhole cameras 1 m apart, rectified, or
with 2 degrees of relative rotation, an off-axis baseline and different lens distortion."""

from __future__ import annotations

import cv2
import numpy as np

from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.rotations import invert_T, make_T

W, H, F = 752, 480, 450.0
K = np.array([[F, 0.0, 376.0], [0.0, F, 240.0], [0.0, 0.0, 1.0]])
BASELINE_M = 1.0


def _rotation_deg(axis: list[float], deg: float) -> np.ndarray:
    a = np.asarray(axis, float)
    R, _ = cv2.Rodrigues(a / np.linalg.norm(a) * np.radians(deg))
    return R


def _camera(D: list[float] | None = None, T_body_cam: np.ndarray | None = None) -> CameraModel:
    T = np.eye(4) if T_body_cam is None else T_body_cam
    if D is None:
        return CameraModel(W, H, K.copy(), T_body_cam=T)
    return CameraModel(
        W, H, K.copy(), D=np.asarray(D, float), distortion_model="plumb_bob", T_body_cam=T
    )


RIGS = {
    "rectified": StereoRig(
        _camera(), _camera(T_body_cam=make_T(np.eye(3), np.array([BASELINE_M, 0.0, 0.0])))
    ),
    # 2 degrees of relative rotation, an off-axis baseline, different lens distortion
    "unrectified": StereoRig(
        _camera([-0.25, 0.07, 0.001, -0.0005, 0.0]),
        _camera(
            [-0.22, 0.05, -0.0008, 0.0004, 0.0],
            make_T(_rotation_deg([0.3, 1.0, 0.2], 2.0), np.array([BASELINE_M, 0.02, 0.01])),
        ),
    ),
}
STACKED = StereoRig(
    _camera(),
    _camera(T_body_cam=make_T(_rotation_deg([1.0, 0.0, 0.0], 1.0), np.array([0.0, 0.5, 0.0]))),
)
"""The right camera 0.5 m below the left one (epipolar lines along v), slightly rotated."""


def to_right(rig: StereoRig, p_left: np.ndarray) -> np.ndarray:
    """(N, 3) left camera coordinates -> right camera coordinates."""
    T = invert_T(rig.T_left_right)
    return p_left @ T[:3, :3].T + T[:3, 3]
