"""Synthetic stereo frames of a rectified rig with a known truth (the tests of
features/disparity_offset.py and features/pixel_noise.py): random points ahead of a car or
below a UAV, seen over consecutive frames with a chosen disparity offset and pixel noise."""

from __future__ import annotations

import numpy as np

from cvslam_cli.geometry.camera import CameraModel, StereoRig, rig_calibration, translation_T
from cvslam_cli.records.features import FeatureSet, FeatureSetBuilder

F_PX, CX, CY, BASELINE_M = 700.0, 600.0, 180.0, 0.5


def rig() -> StereoRig:
    K = np.array([[F_PX, 0, CX], [0, F_PX, CY], [0, 0, 1.0]])
    return StereoRig(
        CameraModel(1200, 360, K), CameraModel(1200, 360, K.copy(), T_body_cam=translation_T(0.5))
    )


def skewed_rig() -> StereoRig:
    """`rig()` with the right camera turned 0.01 rad about x: not rectified."""
    base = rig()
    turned = np.eye(4)
    turned[:3, :3] = [[1, 0, 0], [0, np.cos(0.01), -np.sin(0.01)], [0, np.sin(0.01), np.cos(0.01)]]
    return StereoRig(
        base.left, CameraModel(1200, 360, base.right.K, T_body_cam=base.right.T_body_cam @ turned)
    )


def frames_of(
    offset_px: float,
    *,
    ahead: bool,
    seed: int = 0,
    frames: int = 16,
    noise_px: float = 0.3,
    tail_share: float = 0.0,
    tail_px: float = 0.0,
) -> tuple[FeatureSet, np.ndarray]:
    """Stereo frames of random points with every disparity off by `offset_px`: a camera
    driving forward through a street-like scene (depths 3-120 m, `ahead`) or sliding
    sideways 60 m above flat ground; unique random descriptors per point. Pixel noise:
    Gaussian `noise_px` on each coordinate, and for a share `tail_share` of the keypoints
    `tail_px` instead (a heavy tail, as SIFT's). Also the points (N, 3) in the first
    camera."""
    rng = np.random.default_rng(seed)
    n = 3000
    if ahead:
        P = np.column_stack(
            [rng.uniform(-20, 20, n), rng.uniform(-3, 2, n), rng.uniform(3, 120, n)]
        )
    else:
        P = np.column_stack(
            [rng.uniform(-40, 40, n), rng.uniform(-15, 15 + 2 * frames, n), rng.uniform(59, 61, n)]
        )
    desc = rng.integers(0, 255, (n, 128)).astype(np.uint8)
    builder = FeatureSetBuilder("car", rig_calibration(rig()))
    for k in range(frames):
        Q = P - (np.array([0, 0, 1.2 * k]) if ahead else np.array([0, 2.0 * k, 0]))
        u_l = F_PX * Q[:, 0] / Q[:, 2] + CX
        v = F_PX * Q[:, 1] / Q[:, 2] + CY
        u_r = F_PX * (Q[:, 0] - BASELINE_M) / Q[:, 2] + CX - offset_px
        seen = np.flatnonzero((Q[:, 2] > 1) & (u_l > 0) & (u_l < 1200) & (v > 0) & (v < 360))
        seen = seen[:400]
        m = len(seen)
        e = rng.normal(0, noise_px, (m, 4))
        if tail_share > 0:
            tail = rng.random((m, 4)) < tail_share
            e[tail] *= tail_px / noise_px
        left = np.column_stack([u_l[seen] + e[:, 0], v[seen] + e[:, 1]]).astype(np.float32)
        right = np.column_stack([u_r[seen] + e[:, 2], v[seen] + e[:, 3]]).astype(np.float32)

        def side(uv: np.ndarray, rows: np.ndarray = seen, count: int = m) -> dict:
            return {
                "uv_raw_px": uv,
                "uv_px": uv,
                "size_px": np.ones(count, np.float32),
                "angle_deg": np.zeros(count, np.float32),
                "response": np.ones(count, np.float32),
                "octave": np.zeros(count, np.int32),
                "desc": desc[rows],
            }

        matches = {
            "left": np.arange(m),
            "right": np.arange(m),
            "disparity_px": (left[:, 0] - right[:, 0]).astype(np.float32),
            "distance": np.zeros(m, np.float32),
            "ratio": np.zeros(m, np.float32),
            "p_cam_m": np.zeros((m, 3)),
            "cov_cam_m2": np.tile(np.eye(3), (m, 1, 1)),
            "landmark_id": seen.astype(np.int64),
        }
        builder.add_frame(k * 100_000_000, side(left), side(right), matches)
    return builder.build(), P
