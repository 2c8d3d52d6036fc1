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

from cvslam_cli.records.arrays import (
    F32,
    F64,
    I32,
    I64,
    U8,
    Dim,
    check_increasing,
    check_shape,
)

FORMAT_NAME = "cvslam.features"
FORMAT_VERSION = 1
DESCRIPTOR_SIZE = 128  # SIFT

# every keypoint and match column of a `FeatureSet`, keyed without its `left_` / `right_` /
# `match_` prefix: (shape of one row, dtype); a column not named here is a float32 scalar
_COLUMNS: dict[str, tuple[tuple[int, ...], type[np.generic]]] = {
    "uv_raw_px": ((2,), np.float32),
    "uv_px": ((2,), np.float32),
    "octave": ((), np.int32),
    "desc": ((DESCRIPTOR_SIZE,), np.uint8),
    "left": ((), np.int64),
    "right": ((), np.int64),
    "p_cam_m": ((3,), np.float64),
    "cov_cam_m2": ((3, 3), np.float64),
    "landmark_id": ((), np.int64),
}
_FLOAT32_SCALAR: tuple[tuple[int, ...], type[np.generic]] = ((), np.float32)


@dataclass(frozen=True, eq=False)
class RigCalibration:
    """The stereo calibration the features were made with (copied from the log).

    K: (2, 3, 3) left/right intrinsics; D: (2, 5) distortion (padded with zeros);
    distortion_model: e.g. "plumb_bob"; T_body_cam: (2, 4, 4); size_px: (2, 2) width, height.
    To and from the camera models: `geometry.camera.rig_calibration` / `stereo_rig`.
    """

    K: F64
    D: F64
    distortion_model: str
    T_body_cam: F64
    size_px: I64


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
    left_octave: I32
    left_desc: U8
    right_uv_raw_px: F32
    right_uv_px: F32
    right_size_px: F32
    right_angle_deg: F32
    right_response: F32
    right_octave: I32
    right_desc: U8
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
        """Raise ValueError if shapes, dtypes or offsets are inconsistent (a corrupt file)."""
        for name, shape in (
            ("K", (2, 3, 3)),
            ("D", (2, 5)),
            ("T_body_cam", (2, 4, 4)),
            ("size_px", (2, 2)),
        ):
            check_shape(f"rig.{name}", getattr(self.rig, name), shape, "iuf")
        dims = {"F": self.n_frames, "F+1": self.n_frames + 1}
        check_shape("frame_stamp_ns", self.frame_stamp_ns, ("F",), "iu", dims)
        for name in ("left_offsets", "right_offsets", "match_offsets"):
            off = check_shape(name, getattr(self, name), ("F+1",), "iu", dims)
            if off[0] != 0 or np.any(np.diff(off) < 0):
                raise ValueError(f"{name} must be non-decreasing from 0")
        dims |= {
            "NL": int(self.left_offsets[-1]),
            "NR": int(self.right_offsets[-1]),
            "M": int(self.match_offsets[-1]),
        }
        rows = {"left": "NL", "right": "NR", "match": "M"}
        for name, (prefix, key) in _column_fields().items():
            row_shape, dtype = _COLUMNS.get(key, _FLOAT32_SCALAR)
            shape: tuple[Dim, ...] = (rows[prefix], *row_shape)
            check_shape(name, getattr(self, name), shape, np.dtype(dtype), dims)
        if dims["M"] and (
            self.match_left.max() >= dims["NL"] or self.match_right.max() >= dims["NR"]
        ):
            raise ValueError("match indices point past the keypoint arrays")
        check_increasing("frame_stamp_ns", self.frame_stamp_ns, strict=False)


def _column_fields() -> dict[str, tuple[str, str]]:
    """{field name: (prefix, key)} of the keypoint and match columns of `FeatureSet`."""
    out = {}
    for f in fields(FeatureSet):
        if f.name.startswith(("left_", "right_", "match_")) and not f.name.endswith("offsets"):
            prefix, key = f.name.split("_", 1)
            out[f.name] = (prefix, key)
    return out


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
        arrays: dict[str, np.ndarray] = {}
        for name, (_, key) in _column_fields().items():
            row_shape, dtype = _COLUMNS.get(key, _FLOAT32_SCALAR)
            parts = self._parts.get(name)
            if parts:
                arrays[name] = np.concatenate(parts).astype(dtype, copy=False)
            else:
                arrays[name] = np.zeros((0, *row_shape), dtype=dtype)
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
