"""Projecting a camera image onto the ground: the canvas grid, a frame's footprint, and the
inverse warp (orthorectification).

Canvas (`CanvasGrid`): a north-up map of the nav frame. Pixel (row r, col c) has its centre
at north n = n_max - (r + 0.5) gsd, east e = e_min + (c + 0.5) gsd: columns run east, rows
run south, as GIS tools expect (world files, `io/mosaic_files.py`).

Warp (`warp_to_canvas`): every canvas pixel of the frame's footprint is a ground point
(n, e, z_at(n, e)) of the ground model; it is moved into the camera frame with T_cam_nav and
projected with the camera model (lens distortion included) to a pixel of the raw image, which
`cv2.remap` samples. This inverse mapping needs no ray casting, handles any height field, and
gives each canvas pixel exactly one sample. A ground point is used when it is in front of the
camera, inside the image (less `border_px`), within `max_range_m` horizontally of the camera
and seen at least `min_depression_deg` below the horizon; for a forward-looking camera the
last two keep the part of the image below the horizon and near enough to be resolved.
When the canvas is 2^k times coarser than the image's ground resolution, the image is first
reduced k times by `cv2.pyrDown` so that the remap does not alias.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.projection import project_points, undistort_pixels
from cvslam_cli.mosaic.ground import GroundModel
from cvslam_cli.records.arrays import F64


@dataclass(frozen=True)
class CanvasGrid:
    """North-up raster: `n_max`, `e_min` the north/east of the top-left corner (not the
    pixel centre), `gsd_m` metres per pixel, `shape` (rows, cols)."""

    n_max: float
    e_min: float
    gsd_m: float
    shape: tuple[int, int]

    @classmethod
    def covering(cls, box_ne: F64, gsd_m: float) -> CanvasGrid:
        """The grid of `gsd_m` aligned to multiples of the GSD that covers `box_ne`
        = (n_min, e_min, n_max, e_max)."""
        n0, e0, n1, e1 = (float(x) for x in box_ne)
        e_min = np.floor(e0 / gsd_m) * gsd_m
        n_max = np.ceil(n1 / gsd_m) * gsd_m
        rows = max(1, int(np.ceil((n_max - n0) / gsd_m - 1e-9)))
        cols = max(1, int(np.ceil((e1 - e_min) / gsd_m - 1e-9)))
        return cls(float(n_max), float(e_min), float(gsd_m), (rows, cols))

    @property
    def megapixels(self) -> float:
        return self.shape[0] * self.shape[1] / 1e6

    def box_ne(self) -> F64:
        rows, cols = self.shape
        return np.array(
            [self.n_max - rows * self.gsd_m, self.e_min, self.n_max, self.e_min + cols * self.gsd_m]
        )

    def pixel_of(self, n: F64, e: F64) -> tuple[F64, F64]:
        """(row, col) as floats (pixel centres at integers) of points (n, e)."""
        return (self.n_max - np.asarray(n)) / self.gsd_m - 0.5, (
            np.asarray(e) - self.e_min
        ) / self.gsd_m - 0.5

    def roi_of(self, box_ne: F64) -> tuple[int, int, int, int] | None:
        """(row0, col0, rows, cols) of the canvas pixels whose centres lie in `box_ne`,
        clipped to the canvas; None when empty."""
        n0, e0, n1, e1 = box_ne
        r0 = max(0, int(np.ceil((self.n_max - n1) / self.gsd_m - 0.5)))
        r1 = min(self.shape[0], int(np.floor((self.n_max - n0) / self.gsd_m - 0.5)) + 1)
        c0 = max(0, int(np.ceil((e0 - self.e_min) / self.gsd_m - 0.5)))
        c1 = min(self.shape[1], int(np.floor((e1 - self.e_min) / self.gsd_m - 0.5)) + 1)
        if r1 <= r0 or c1 <= c0:
            return None
        return r0, c0, r1 - r0, c1 - c0

    def sub(self, roi: tuple[int, int, int, int]) -> CanvasGrid:
        """The grid of a sub-rectangle (row0, col0, rows, cols) of this one."""
        r0, c0, h, w = roi
        return CanvasGrid(
            self.n_max - r0 * self.gsd_m, self.e_min + c0 * self.gsd_m, self.gsd_m, (h, w)
        )


@dataclass(frozen=True)
class ViewLimits:
    """Which ground a camera contributes (module docstring)."""

    max_range_m: float
    min_depression_deg: float
    border_px: int


def _border_pixels(cam: CameraModel, per_side: int = 12) -> F64:
    """(M, 2) pixels along the image border and a coarse interior grid."""
    u = np.linspace(0, cam.width - 1, per_side)
    v = np.linspace(0, cam.height - 1, per_side)
    uu, vv = np.meshgrid(u, v)
    return np.c_[uu.ravel(), vv.ravel()]


def ground_hits(
    cam: CameraModel, T_nav_cam: F64, ground: GroundModel, uv_px: F64, limits: ViewLimits
) -> tuple[F64, NDArray[np.bool_]]:
    """(M, 3) ground points hit by the rays of pixels `uv_px` (M, 2), and which are valid
    (below the horizon by the minimum depression, within range). Intersection with the
    height field by fixed-point iteration from the height under the camera."""
    xy = undistort_pixels(cam, uv_px)
    d = np.c_[xy, np.ones(len(xy))] @ T_nav_cam[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = T_nav_cam[:3, 3]
    sin_dep = np.sin(np.radians(max(limits.min_depression_deg, 0.1)))
    down = d[:, 2] >= sin_dep  # NED: z down
    z = np.full(len(d), float(ground.z_at(c[0], c[1])))
    p = np.tile(c, (len(d), 1))
    for _ in range(8):
        s = np.where(down, (z - c[2]) / np.where(down, d[:, 2], 1.0), np.nan)
        p = c + s[:, None] * d
        z = ground.z_at(p[:, 0], p[:, 1])
    ok = down & np.isfinite(s) & (s > 0)
    horiz = np.hypot(p[:, 0] - c[0], p[:, 1] - c[1])
    ok &= horiz <= limits.max_range_m
    return p, ok


def footprint_box(
    cam: CameraModel, T_nav_cam: F64, ground: GroundModel, limits: ViewLimits
) -> F64 | None:
    """(n_min, e_min, n_max, e_max) of the ground the frame covers, or None. Sample rays
    that miss the ground within range (above the horizon, or far) bound it by the point at
    the range limit in their horizontal direction; the box is grown by 2 % for the ground
    between the samples. The exact coverage is decided per canvas pixel in the warp."""
    uv = _border_pixels(cam)
    p, ok = ground_hits(cam, T_nav_cam, ground, uv, limits)
    if not ok.any():
        return None
    c = T_nav_cam[:3, 3]
    pts = p[ok, :2]
    if not ok.all():
        d = np.c_[undistort_pixels(cam, uv[~ok]), np.ones(int((~ok).sum()))] @ T_nav_cam[:3, :3].T
        h = d[:, :2]
        norm = np.linalg.norm(h, axis=1)
        h = h[norm > 1e-9] / norm[norm > 1e-9, None]
        pts = np.vstack([pts, c[:2] + limits.max_range_m * h])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.02 * (hi - lo)
    return np.r_[lo - pad, hi + pad]


def image_gsd_m(cam: CameraModel, T_nav_cam: F64, ground: GroundModel, limits: ViewLimits) -> float:
    """The image's own ground resolution [m/px]: the median over its valid sample pixels of
    the side of the ground square a pixel covers, depth / (f sqrt(cos incidence)), with the
    incidence angle between the ray and the ground's normal (a nadir view: depth / f; an
    oblique one is coarser along the line of sight); NaN when it sees no ground."""
    uv = _border_pixels(cam, 8)
    p, ok = ground_hits(cam, T_nav_cam, ground, uv, limits)
    if not ok.any():
        return float("nan")
    rel = p[ok] - T_nav_cam[:3, 3]
    dist = np.linalg.norm(rel, axis=1)
    depth = rel @ T_nav_cam[:3, 2]
    _, b, c = ground.global_abc
    normal = np.array([-b, -c, 1.0]) / np.sqrt(1.0 + b * b + c * c)
    cos_inc = np.abs(rel @ normal) / np.maximum(dist, 1e-12)
    side = depth / (np.sqrt(cam.fx * cam.fy) * np.sqrt(np.maximum(cos_inc, 1e-3)))
    return float(np.median(side))


def _upsample(coarse: NDArray, step: int, h: int, w: int) -> NDArray[np.float32]:
    """Bilinear interpolation of values at nodes (i * step, j * step) to every pixel of an
    (h, w) patch (NaN nodes make their neighbourhood NaN)."""
    qr = np.arange(h, dtype=np.float32) / step
    qc = np.arange(w, dtype=np.float32) / step
    map_r = np.ascontiguousarray(np.broadcast_to(qr[:, None], (h, w)))
    map_c = np.ascontiguousarray(np.broadcast_to(qc[None, :], (h, w)))
    return cv2.remap(
        np.ascontiguousarray(coarse, np.float32),
        map_c,
        map_r,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def warp_to_canvas(
    image: NDArray,
    cam: CameraModel,
    T_nav_cam: F64,
    ground: GroundModel,
    grid: CanvasGrid,
    roi: tuple[int, int, int, int],
    limits: ViewLimits,
    *,
    step: int = 8,
) -> tuple[NDArray, NDArray[np.uint8]]:
    """The image resampled on canvas pixels `roi` = (row0, col0, rows, cols): (rows, cols
    [, 3]) of the image's dtype, and a uint8 mask (255 where valid). The projection is
    computed exactly at every `step`-th canvas pixel and interpolated bilinearly between
    (it is smooth: the error is far below a pixel for steps of a few pixels)."""
    r0, c0, h, w = roi
    hc, wc = (h - 1) // step + 2, (w - 1) // step + 2
    rows = r0 + step * np.arange(hc, dtype=np.float64)
    cols = c0 + step * np.arange(wc, dtype=np.float64)
    n = (grid.n_max - (rows + 0.5) * grid.gsd_m)[:, None]
    e = (grid.e_min + (cols + 0.5) * grid.gsd_m)[None, :]
    n, e = np.broadcast_arrays(n, e)
    z = ground.z_at(n, e)
    c = T_nav_cam[:3, 3]
    rel = np.stack([n - c[0], e - c[1], z - c[2]], axis=-1).reshape(-1, 3)
    p_cam = rel @ T_nav_cam[:3, :3]  # = (R_nav_cam^T rel^T)^T
    uv, front = project_points(cam, p_cam)
    dist = np.linalg.norm(rel, axis=1)
    # per node: u, v, horizontal distance, sin(depression); invalid projections NaN
    uv = np.where(front[:, None], uv, np.nan)
    nodes = np.stack(
        [uv[:, 0], uv[:, 1], np.hypot(rel[:, 0], rel[:, 1]), rel[:, 2] / np.maximum(dist, 1e-9)],
        axis=-1,
    ).reshape(hc, wc, 4)
    fine = _upsample(nodes, step, h, w)
    map_u, map_v, horiz, sin_dep = (fine[..., k] for k in range(4))
    b = limits.border_px
    with np.errstate(invalid="ignore"):
        valid = (
            (map_u >= b)
            & (map_u <= cam.width - 1 - b)
            & (map_v >= b)
            & (map_v <= cam.height - 1 - b)
            & (sin_dep >= np.sin(np.radians(limits.min_depression_deg)))
            & (horiz <= limits.max_range_m)
        )
    # reduce the image where the canvas is much coarser than it (no aliasing)
    ok_nodes = front & np.isfinite(dist)
    img_gsd = np.median(dist[ok_nodes]) / np.sqrt(cam.fx * cam.fy) if ok_nodes.any() else grid.gsd_m
    ratio = grid.gsd_m / max(float(img_gsd), 1e-9)
    level = int(np.clip(np.floor(np.log2(max(ratio, 1.0))), 0, 6))
    src = image
    for _ in range(level):
        src = cv2.pyrDown(src)
    if level:
        scale = np.float32(1.0 / (1 << level))
        map_u = (map_u + 0.5) * scale - 0.5
        map_v = (map_v + 0.5) * scale - 0.5
    map_u = np.where(valid, map_u, -1.0).astype(np.float32)
    map_v = np.where(valid, map_v, -1.0).astype(np.float32)
    out = cv2.remap(src, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out, np.where(valid, 255, 0).astype(np.uint8)
