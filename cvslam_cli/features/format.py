"""The feature format: what `cvslam extract` (and `cvslam simulate` in landmark mode) writes
for one vehicle, and what `cvslam fuse` reads. Documented in `docs/feature_format.md`.

All frames of one vehicle are stored as flat arrays with CSR-style offsets: the keypoints
of frame i are rows `left_offsets[i]:left_offsets[i+1]` of the `left_*` arrays, and so on.
Match indices are *global* row indices into the keypoint arrays.

Coordinates: `*_uv_raw_px` are pixel coordinates in the recorded (distorted) image;
`*_uv_px` are the same points undistorted, in ideal pinhole pixels of that camera's own K
(no rectification): u = fx x/z + cx, v = fy y/z + cy, which is exactly the observation
model of the paper (eq. 19). `match_p_cam_m` is the triangulated point in the LEFT camera
optical frame (inverse observation model) and `match_cov_cam_m2` its covariance propagated
from the pixel noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.camera import CameraModel, StereoRig

FORMAT_NAME = "cvslam.features"
FORMAT_VERSION = 1
DESCRIPTOR_SIZE = 128  # SIFT

I64 = NDArray[np.int64]
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """The stereo calibration the features were made with (copied from the log).

    K: (2, 3, 3) left/right intrinsics; D: (2, 5) distortion (padded with zeros);
    distortion_model: e.g. "plumb_bob"; T_body_cam: (2, 4, 4); size_px: (2, 2) width, height.
    """

    K: F64
    D: F64
    distortion_model: str
    T_body_cam: F64
    size_px: NDArray[np.int64]


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


@dataclass(frozen=True, eq=False)
class FeatureSet:
    """Features of all stereo frames of one vehicle.

    F frames, NL / NR keypoints in all, M accepted stereo matches in all.

    frame_stamp_ns (F,) int64: left image stamps.
    left_offsets, right_offsets, match_offsets (F+1,) int64: CSR offsets per frame.
    left_uv_raw_px, left_uv_px (NL, 2) float32; left_size_px, left_angle_deg,
        left_response (NL,) float32; left_octave (NL,) int32; left_desc (NL, 128) uint8.
    right_* likewise with NR rows.
    match_left, match_right (M,) int64: global keypoint rows.
    match_disparity_px (M,) float32: left u minus right u (undistorted pixels).
    match_distance (M,) float32: descriptor distance D1; match_ratio (M,) float32: D1 / D2.
    match_p_cam_m (M, 3) float64: triangulated point, left camera frame.
    match_cov_cam_m2 (M, 3, 3) float64: its covariance.
    match_landmark_id (M,) int64: true landmark id when known (simulator), else -1;
        an outlier match injected by the simulator has id -2.
    """

    vehicle: str
    rig: RigCalibration
    frame_stamp_ns: I64
    left_offsets: I64
    right_offsets: I64
    match_offsets: I64
    left_uv_raw_px: F32
    left_uv_px: F32
    left_size_px: F32
    left_angle_deg: F32
    left_response: F32
    left_octave: NDArray[np.int32]
    left_desc: NDArray[np.uint8]
    right_uv_raw_px: F32
    right_uv_px: F32
    right_size_px: F32
    right_angle_deg: F32
    right_response: F32
    right_octave: NDArray[np.int32]
    right_desc: NDArray[np.uint8]
    match_left: I64
    match_right: I64
    match_disparity_px: F32
    match_distance: F32
    match_ratio: F32
    match_p_cam_m: F64
    match_cov_cam_m2: F64
    match_landmark_id: I64

    @property
    def n_frames(self) -> int:
        return int(self.frame_stamp_ns.shape[0])

    def frame_matches(self, i: int) -> slice:
        return slice(int(self.match_offsets[i]), int(self.match_offsets[i + 1]))

    def validate(self) -> None:
        """Raise ValueError if shapes or offsets are inconsistent (a corrupt file)."""
        F = self.n_frames
        for name in ("left_offsets", "right_offsets", "match_offsets"):
            off = getattr(self, name)
            if off.shape != (F + 1,) or off[0] != 0 or np.any(np.diff(off) < 0):
                raise ValueError(f"{name} must be ({F + 1},) non-decreasing from 0")
        nl, nr, m = (
            int(self.left_offsets[-1]),
            int(self.right_offsets[-1]),
            int(self.match_offsets[-1]),
        )
        for f in fields(self):
            if f.name.startswith(("left_", "right_", "match_")) and not f.name.endswith("offsets"):
                arr = getattr(self, f.name)
                n = {"left": nl, "right": nr, "match": m}[f.name.split("_")[0]]
                if arr.shape[0] != n:
                    raise ValueError(f"{f.name} has {arr.shape[0]} rows, expected {n}")
        if self.left_desc.shape[1:] != (DESCRIPTOR_SIZE,) or self.left_desc.dtype != np.uint8:
            raise ValueError(f"left_desc must be (NL, {DESCRIPTOR_SIZE}) uint8")
        if m and (self.match_left.max() >= nl or self.match_right.max() >= nr):
            raise ValueError("match indices point past the keypoint arrays")
        if np.any(np.diff(self.frame_stamp_ns) < 0):
            raise ValueError("frame stamps are not in time order")


@dataclass
class FeatureSetBuilder:
    """Accumulates frames (in time order) and builds a `FeatureSet`."""

    vehicle: str
    rig: RigCalibration
    _stamps: list[int] = field(default_factory=list)
    _parts: dict[str, list[np.ndarray]] = field(default_factory=dict)
    _counts: dict[str, list[int]] = field(
        default_factory=lambda: {"left": [0], "right": [0], "match": [0]}
    )

    def add_frame(
        self,
        stamp_ns: int,
        left: dict[str, np.ndarray],
        right: dict[str, np.ndarray],
        matches: dict[str, np.ndarray],
    ) -> None:
        """`left`/`right`: arrays keyed like the FeatureSet fields without the side prefix
        (uv_raw_px, uv_px, size_px, angle_deg, response, octave, desc); `matches`: keyed
        without `match_` and with *frame-local* left/right indices."""
        self._stamps.append(int(stamp_ns))
        nl0, nr0 = self._counts["left"][-1], self._counts["right"][-1]
        for prefix, data in (("left", left), ("right", right), ("match", matches)):
            n = None
            for key, arr in data.items():
                value = np.asarray(arr)
                if prefix == "match" and key == "left":
                    value = value.astype(np.int64) + nl0
                elif prefix == "match" and key == "right":
                    value = value.astype(np.int64) + nr0
                self._parts.setdefault(f"{prefix}_{key}", []).append(value)
                n = value.shape[0]
            self._counts[prefix].append(self._counts[prefix][-1] + (n or 0))

    def build(self) -> FeatureSet:
        dtypes = {f.name: f for f in fields(FeatureSet)}
        shapes = {
            "uv_raw_px": (2,),
            "uv_px": (2,),
            "desc": (DESCRIPTOR_SIZE,),
            "p_cam_m": (3,),
            "cov_cam_m2": (3, 3),
        }
        kinds = {
            "desc": np.uint8,
            "octave": np.int32,
            "left": np.int64,
            "right": np.int64,
            "landmark_id": np.int64,
            "p_cam_m": np.float64,
            "cov_cam_m2": np.float64,
        }
        arrays: dict[str, np.ndarray] = {}
        for name in dtypes:
            if not name.startswith(("left_", "right_", "match_")) or name.endswith("offsets"):
                continue
            key = name.split("_", 1)[1]
            dtype = kinds.get(key, np.float32)
            parts = self._parts.get(name)
            if parts:
                arrays[name] = np.concatenate(parts).astype(dtype, copy=False)
            else:
                arrays[name] = np.zeros((0, *shapes.get(key, ())), dtype=dtype)
        fs = FeatureSet(
            vehicle=self.vehicle,
            rig=self.rig,
            frame_stamp_ns=np.asarray(self._stamps, dtype=np.int64),
            left_offsets=np.asarray(self._counts["left"], dtype=np.int64),
            right_offsets=np.asarray(self._counts["right"], dtype=np.int64),
            match_offsets=np.asarray(self._counts["match"], dtype=np.int64),
            **arrays,
        )
        fs.validate()
        return fs
