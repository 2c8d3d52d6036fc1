"""The ground-robot world ("yard") and its forward-looking camera views.

The paper's ground experiment drives Pioneer robots along overlapping paths through a scene
of textured vertical surfaces and ground. The simulated yard is:

- the ground, the plane z = 0 of the nav frame (NED: x north, y east, z down), textured like
  concrete/asphalt (fractal noise, slabs, painted lines, stains, cracks) over the rectangle
  `origin_nav_m` + [0, size_m], widened by `ground_margin_m` on every side (the paved ground
  beyond the walls, which a camera above them sees: a UAV's);
- four perimeter walls along that rectangle and `n_obstacles` free-standing obstacles
  inside it (thin two-sided panels and boxes of four faces), all vertical rectangles standing
  on the ground, from z = -height to z = 0. Each wall texture is a sequence of segments,
  busy (bricks, posters, shelves, signs, doors and windows) or plain (painted concrete), so
  that the feature density along a path varies.

Texture conventions (texel centres at half-integers of metres * px_per_m, so that a
continuous texture coordinate is `metres * px_per_m - 0.5` in OpenCV's pixel convention):
- ground texture (Hg, Wg): row <-> north, col <-> east, from `YardSpec.ground_origin_nav_m`
  (`origin_nav_m` less the margin);
- wall texture (Ht, Wt): col <-> distance s along the wall from `p0_ne` towards `p1_ne`,
  row <-> distance *below the top of the wall* (row 0 at z = -height_m, the last row at the
  ground). Outside a texture the edge texel is repeated (clamp).

Rendering (`render_yard_view`) is exact ray casting of every raw pixel: the pixel's ray
(x/z, y/z, 1) from `pixel_rays` (distortion included) is rotated into the nav frame and
intersected with the ground plane and with every wall. A ray point at parameter t has camera
depth z = t (the ray's camera z component is 1), so the nearest hit is the smallest positive
t. Walls are culled per image: a wall's quadrilateral, clipped to the half space in front of
the camera, projects to a convex polygon in the normalised image plane; only the image rows
and columns whose rays can fall in that polygon's bounding box are tested. Radiance is a
bilinear lookup (one `cv2.remap`) in an atlas holding the ground and every wall texture with a
replicated border; pixels that hit nothing (or the ground beyond `max_range_m`) see a smooth
sky and get NaN depth. There is no anti-aliasing: far surfaces are point-sampled.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.config import opt
from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.projection import pixel_rays
from cvslam_cli.records.arrays import F32, F64, U8
from cvslam_cli.sim.render import RenderResult
from cvslam_cli.sim.texture import busy_texture, fractal_noise, to_uint8

NEAR_M = 1e-3  # hits nearer than this to the optical centre are ignored
MAX_TEXTURE_PX = 16000  # per texture dimension (cv2.remap addresses at most 32767)
MAX_GROUND_TEXELS = 36_000_000  # e.g. 150 m x 150 m at 40 px/m
_ATLAS_PAD = 2  # replicated border around every atlas tile
_ATLAS_WIDTH_MIN = 2048


@dataclass(frozen=True)
class YardSpec:
    """Parameters of the yard (scenario key `yard`).

    size_m: (north, east) extent of the yard, metres. origin_nav_m: (north, east) of its
    south-west corner. wall_height_m: height of the perimeter walls (obstacles are at most
    this tall). n_obstacles: free-standing panels and boxes inside. texture_px_per_m,
    ground_px_per_m: texel density of wall and ground textures. obstacle_clearance_m: the
    smallest gap left between obstacles, and between an obstacle and the perimeter walls.
    busy_fraction: share of wall segments with busy content (bricks, posters, shelves, signs,
    doors and windows); the rest are plain painted concrete. ground_margin_m: how far the
    textured ground extends beyond the perimeter walls on every side; 0 (ground robots only:
    their walls hide what lies beyond) ends it at the walls, where the edge texels repeat.
    """

    size_m: tuple[float, float] = opt((40.0, 40.0))
    origin_nav_m: tuple[float, float] = opt((-20.0, -20.0))
    wall_height_m: float = opt(2.5, lo=0.0, lo_open=True)
    n_obstacles: int = opt(8, lo=0)
    texture_px_per_m: float = opt(60.0, lo=0.0, lo_open=True)
    ground_px_per_m: float = opt(40.0, lo=0.0, lo_open=True)
    obstacle_clearance_m: float = opt(2.5, lo=0.0)
    busy_fraction: float = opt(0.6, lo=0.0, hi=1.0)
    ground_margin_m: float = opt(0.0, lo=0.0)

    @property
    def ground_origin_nav_m(self) -> tuple[float, float]:
        """(north, east) of the south-west corner of the textured ground."""
        m = float(self.ground_margin_m)
        return (float(self.origin_nav_m[0]) - m, float(self.origin_nav_m[1]) - m)

    @property
    def ground_size_m(self) -> tuple[float, float]:
        """(north, east) extent of the textured ground: the yard and its margins."""
        m = 2.0 * float(self.ground_margin_m)
        return (float(self.size_m[0]) + m, float(self.size_m[1]) + m)

    def check(self) -> None:
        """Raise `ValueError` saying what is wrong if no yard can be built from this spec."""
        if len(self.size_m) != 2 or len(self.origin_nav_m) != 2:
            raise ValueError(
                f"yard: size_m and origin_nav_m must be (north, east) pairs, got "
                f"{self.size_m!r} and {self.origin_nav_m!r}"
            )
        sn, se = (float(v) for v in self.size_m)
        if not (math.isfinite(sn) and math.isfinite(se) and sn > 0 and se > 0):
            raise ValueError(f"yard: size_m must be two positive numbers, got {self.size_m!r}")
        if not all(math.isfinite(float(v)) for v in self.origin_nav_m):
            raise ValueError(f"yard: origin_nav_m must be finite, got {self.origin_nav_m!r}")
        for name in ("wall_height_m", "texture_px_per_m", "ground_px_per_m"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"yard: {name} must be a positive number, got {value:g}")
        if int(self.n_obstacles) != self.n_obstacles or self.n_obstacles < 0:
            raise ValueError(f"yard: n_obstacles must be an integer >= 0, got {self.n_obstacles}")
        if not (math.isfinite(self.obstacle_clearance_m) and self.obstacle_clearance_m >= 0):
            raise ValueError(
                f"yard: obstacle_clearance_m must be >= 0, got {self.obstacle_clearance_m:g}"
            )
        if not 0.0 <= self.busy_fraction <= 1.0:
            raise ValueError(f"yard: busy_fraction must be in [0, 1], got {self.busy_fraction:g}")
        if not (math.isfinite(self.ground_margin_m) and self.ground_margin_m >= 0):
            raise ValueError(f"yard: ground_margin_m must be >= 0, got {self.ground_margin_m:g}")
        wall_px = max(sn, se) * self.texture_px_per_m
        if wall_px > MAX_TEXTURE_PX or self.wall_height_m * self.texture_px_per_m > MAX_TEXTURE_PX:
            raise ValueError(
                f"yard: a {max(sn, se):g} m x {self.wall_height_m:g} m wall at "
                f"texture_px_per_m={self.texture_px_per_m:g} needs a texture over "
                f"{MAX_TEXTURE_PX} px; reduce size_m or texture_px_per_m"
            )
        gsn, gse = self.ground_size_m
        gn, ge = gsn * self.ground_px_per_m, gse * self.ground_px_per_m
        if max(gn, ge) > MAX_TEXTURE_PX or gn * ge > MAX_GROUND_TEXELS:
            raise ValueError(
                f"yard: the {gsn:g} m x {gse:g} m ground at ground_px_per_m="
                f"{self.ground_px_per_m:g} needs a {gn:.0f} x {ge:.0f} texture (at most "
                f"{MAX_TEXTURE_PX} px a side and {MAX_GROUND_TEXELS} texels); reduce size_m, "
                f"ground_margin_m or ground_px_per_m"
            )
        min_side = 2.0 * self.obstacle_clearance_m + 1.0
        if self.n_obstacles > 0 and min(sn, se) < min_side:
            raise ValueError(
                f"yard: a {sn:g} m x {se:g} m yard has no room for obstacles with "
                f"{self.obstacle_clearance_m:g} m clearance (needs at least {min_side:g} m a "
                f"side); set n_obstacles: 0 or enlarge size_m"
            )


@dataclass(frozen=True, eq=False)
class Wall:
    """One vertical textured rectangle standing on the ground.

    p0_ne, p1_ne: (2,) float64 endpoints (north, east) in metres, nav frame. The wall spans
    z in [-height_m, 0]. texture: (Ht, Wt) uint8 with Ht = ceil(height_m * px_per_m),
    Wt = ceil(length_m * px_per_m); col <-> distance s from p0 along p0 -> p1, row <-> distance
    below the top of the wall (row 0 at the top). Both faces show the same texture.
    kind: "perimeter", "panel" or "box".
    """

    p0_ne: F64
    p1_ne: F64
    height_m: float
    texture: U8
    px_per_m: float
    kind: str = "perimeter"

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.p1_ne - self.p0_ne))

    @property
    def direction_ne(self) -> F64:
        """(2,) unit vector from p0 to p1."""
        d = self.p1_ne - self.p0_ne
        return d / np.linalg.norm(d)

    def point_nav_m(self, s_m: F64, h_m: F64) -> F64:
        """(N, 3) nav-frame points at distance s_m along the wall and h_m above the ground."""
        s = np.asarray(s_m, dtype=float).reshape(-1)
        h = np.asarray(h_m, dtype=float).reshape(-1)
        ne = self.p0_ne[None, :] + s[:, None] * self.direction_ne[None, :]
        return np.column_stack([ne, -h])


def _bilinear_clamped(tex: U8, row: F64, col: F64) -> F32:
    """Bilinear sample of `tex` at continuous (row, col), edge texels repeated; in [0, 1]."""
    h, w = tex.shape
    r0 = np.floor(row)
    c0 = np.floor(col)
    fr = (row - r0).astype(np.float32)
    fc = (col - c0).astype(np.float32)
    r0i = r0.astype(np.int64)
    c0i = c0.astype(np.int64)
    ra, rb = np.clip(r0i, 0, h - 1), np.clip(r0i + 1, 0, h - 1)
    ca, cb = np.clip(c0i, 0, w - 1), np.clip(c0i + 1, 0, w - 1)
    t = tex.astype(np.float32) / np.float32(255.0)
    top = t[ra, ca] * (1 - fc) + t[ra, cb] * fc
    bot = t[rb, ca] * (1 - fc) + t[rb, cb] * fc
    return (top * (1 - fr) + bot * fr).astype(np.float32)


@dataclass(frozen=True, eq=False)
class _Atlas:
    """All textures of a yard in one float32 image, for a single `cv2.remap` per view.

    image: (Ha, Wa) float32 in [0, 1]. ground_rc: (row, col) of ground texel (0, 0).
    wall_rc: (n_walls, 2) of each wall's texel (0, 0).
    """

    image: F32
    ground_rc: tuple[int, int]
    wall_rc: NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class Yard:
    """A generated yard.

    walls: the four perimeter walls (south, east, north, west) then the obstacle faces.
    ground_texture: (Hg, Wg) uint8, row <-> north, col <-> east from
    `spec.ground_origin_nav_m`, at `spec.ground_px_per_m`. obstacles_ne: per obstacle its
    footprint, (2, 2) endpoints of a panel or (4, 2) corners of a box (north, east, metres,
    in order around the box).
    """

    spec: YardSpec
    walls: tuple[Wall, ...]
    ground_texture: U8
    obstacles_ne: tuple[F64, ...] = ()

    def ground_texture_at(self, n_m: F64, e_m: F64) -> F32:
        """Ground radiance in [0, 1] (bilinear, clamped at the ground's edge) at nav (n, e)."""
        ppm = self.spec.ground_px_per_m
        n0, e0 = self.spec.ground_origin_nav_m
        row = (np.asarray(n_m, dtype=float) - n0) * ppm - 0.5
        col = (np.asarray(e_m, dtype=float) - e0) * ppm - 0.5
        return _bilinear_clamped(self.ground_texture, row, col)

    def wall_texture_at(self, i: int, s_m: F64, h_m: F64) -> F32:
        """Radiance in [0, 1] of wall `i` at distance s_m from p0 and h_m above the ground."""
        wall = self.walls[i]
        col = np.asarray(s_m, dtype=float) * wall.px_per_m - 0.5
        row = (wall.height_m - np.asarray(h_m, dtype=float)) * wall.px_per_m - 0.5
        return _bilinear_clamped(wall.texture, row, col)

    def free_space_ok(
        self, n_m: float | F64, e_m: float | F64, margin_m: float = 0.0
    ) -> bool | NDArray[np.bool_]:
        """Whether nav point(s) (n, e) are drivable: inside the yard, at least `margin_m` from
        every wall (horizontal distance to the wall segment) and not inside a box. Scalars
        give a bool, arrays an array of bools of their broadcast shape."""
        n, e = np.broadcast_arrays(np.asarray(n_m, dtype=float), np.asarray(e_m, dtype=float))
        shape = n.shape
        p = np.stack([n.reshape(-1), e.reshape(-1)], axis=1)
        n0, e0 = self.spec.origin_nav_m
        sn, se = self.spec.size_m
        ok = (
            (p[:, 0] >= n0 + margin_m)
            & (p[:, 0] <= n0 + sn - margin_m)
            & (p[:, 1] >= e0 + margin_m)
            & (p[:, 1] <= e0 + se - margin_m)
        )
        if self.walls:
            a = np.stack([w.p0_ne for w in self.walls])  # (M, 2)
            b = np.stack([w.p1_ne for w in self.walls])
            ab = b - a
            ap = p[:, None, :] - a[None, :, :]  # (N, M, 2)
            s = np.clip(np.einsum("nmk,mk->nm", ap, ab) / np.einsum("mk,mk->m", ab, ab), 0, 1)
            d = np.linalg.norm(ap - s[..., None] * ab[None, :, :], axis=2)
            ok &= np.all(d >= margin_m, axis=1)
        for poly in self.obstacles_ne:
            if len(poly) < 3:
                continue
            edges = np.roll(poly, -1, axis=0) - poly  # (k, 2)
            rel = p[:, None, :] - poly[None, :, :]  # (N, k, 2)
            cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
            inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
            ok &= ~inside
        if shape == ():
            return bool(ok[0])
        return ok.reshape(shape)

    @cached_property
    def _atlas(self) -> _Atlas:
        return _build_atlas(self)


# --------------------------------------------------------------------------- generation


def _wall_background(shape: tuple[int, int], rng: np.random.Generator, ppm: float) -> F32:
    """Painted concrete: a paint shade, gentle mottling, grain and grime near the ground."""
    h = shape[0]
    paint = float(rng.uniform(0.4, 0.75))
    mottle = fractal_noise(shape, rng, base_px=max(2.0, 1.5 * ppm), octaves=4)
    grain = fractal_noise(shape, rng, base_px=2.0, octaves=2)
    img = paint + 0.12 * (mottle - 0.5) + 0.06 * (grain - 0.5)
    rows_from_top = np.arange(h, dtype=np.float32)[:, None]
    height_above_ground_m = (h - 0.5 - rows_from_top) / ppm
    grime = 0.12 * np.exp(-height_above_ground_m / 0.25)
    return np.asarray(img - grime, dtype=np.float32)


def _bricks(shape: tuple[int, int], rng: np.random.Generator, ppm: float) -> F32:
    """Bricks or cinder blocks in running bond, each a shade of its own, mortar joints."""
    h, w = shape
    if rng.random() < 0.5:
        bw_m, bh_m = rng.uniform(0.22, 0.3), rng.uniform(0.07, 0.09)
    else:
        bw_m, bh_m = rng.uniform(0.38, 0.45), rng.uniform(0.18, 0.22)
    bw, bh = max(4, round(bw_m * ppm)), max(3, round(bh_m * ppm))
    joint = max(1, round(0.012 * ppm))
    rr, cc = np.mgrid[0:h, 0:w]
    course = rr // bh
    shifted = cc + (course % 2) * (bw // 2)
    brick = shifted // bw
    base = float(rng.uniform(0.3, 0.65))
    shades = base + rng.uniform(-0.12, 0.12, (course.max() + 1, brick.max() + 1))
    img = shades[course, brick].astype(np.float32)
    mortar = ((rr % bh) < joint) | ((shifted % bw) < joint)
    img[mortar] = float(np.clip(base + rng.choice([-0.2, 0.2]), 0.05, 0.95))
    img += 0.05 * (fractal_noise(shape, rng, base_px=3.0, octaves=2) - 0.5)
    return img


def _text_marks(
    img: F32, rng: np.random.Generator, x0: int, y0: int, x1: int, y1: int, ppm: float
) -> None:
    """Rows of word-like dark or light marks inside [x0, x1) x [y0, y1)."""
    line_px = max(3, round(rng.uniform(0.04, 0.09) * ppm))
    ink = float(rng.choice([0.05, 0.95]))
    y = y0 + line_px
    while y + line_px < y1:
        x = x0 + line_px
        while x < x1 - line_px:
            word = max(2, round(rng.uniform(0.5, 4.0) * line_px))
            if x + word >= x1 - line_px:
                break
            cv2.rectangle(img, (x, y), (x + word, y + int(0.7 * line_px)), ink, -1)
            x += word + max(2, line_px // 2)
        y += 2 * line_px


def _posters(img: F32, rng: np.random.Generator, ppm: float) -> None:
    """Framed posters (busy pictures) and notices (text) in one or two rows, in place."""
    h, w = img.shape
    n_rows = 2 if h > 2.0 * ppm and rng.random() < 0.5 else 1
    band = h // n_rows
    for k in range(n_rows):
        x = int(rng.uniform(0.05, 0.4) * ppm)
        while x < w - 0.3 * ppm:
            pw = int(rng.uniform(0.3, 1.0) * ppm)
            ph = int(rng.uniform(0.3, 0.9) * ppm)
            pw, ph = min(pw, w - x - 1), min(ph, band - 2)
            if pw < 6 or ph < 6:
                break
            top = k * band + int(rng.uniform(0.05, 0.6) * max(1, band - ph))
            if rng.random() < 0.6:
                pic = busy_texture((ph, pw), rng, px_per_m=ppm / rng.uniform(12.0, 30.0))
                lo, hi = rng.uniform(0.0, 0.3), rng.uniform(0.7, 1.0)
                img[top : top + ph, x : x + pw] = lo + (hi - lo) * pic
            else:
                img[top : top + ph, x : x + pw] = float(rng.uniform(0.75, 0.95))
                _text_marks(img, rng, x, top, x + pw, top + ph, ppm)
            frame = max(1, round(0.015 * ppm))
            cv2.rectangle(img, (x, top), (x + pw - 1, top + ph - 1), 0.1, frame)
            x += pw + int(rng.uniform(0.1, 0.6) * ppm)


def _shelves(img: F32, rng: np.random.Generator, ppm: float) -> None:
    """Shelving: boards with shadows, boxes and labels of varied size and shade, in place."""
    h, w = img.shape
    board = max(2, round(0.03 * ppm))
    y = h - 1 - int(0.15 * ppm)  # rows count from the top; the lowest board near the ground
    while y > 0.2 * ppm:
        cv2.rectangle(img, (0, y), (w - 1, y + board), float(rng.uniform(0.15, 0.35)), -1)
        cv2.rectangle(img, (0, y + board + 1), (w - 1, y + 2 * board), 0.08, -1)
        x = int(rng.uniform(0.0, 0.2) * ppm)
        while x < w:
            bw = int(rng.uniform(0.08, 0.5) * ppm)
            bh = int(rng.uniform(0.08, 0.35) * ppm)
            if rng.random() < 0.8:
                cv2.rectangle(img, (x, y - bh), (x + bw, y - 1), float(rng.uniform(0.1, 0.95)), -1)
                if bw > 8 and bh > 8 and rng.random() < 0.5:
                    lx, ly = x + bw // 4, y - 3 * bh // 4
                    shade = float(rng.uniform(0.0, 1.0))
                    cv2.rectangle(img, (lx, ly), (lx + bw // 2, ly + bh // 4), shade, -1)
            x += bw + int(rng.uniform(0.0, 0.1) * ppm)
        y -= int(rng.uniform(0.35, 0.6) * ppm)


def _signs(img: F32, rng: np.random.Generator, ppm: float) -> None:
    """Sign boards with lettering and a pictogram, about one per 1.5 m, in place."""
    h, w = img.shape
    for _ in range(max(1, int(w / (1.5 * ppm)))):
        sw = int(min(w - 2, rng.uniform(0.6, 2.0) * ppm))
        sh = int(min(h - 2, rng.uniform(0.3, 0.8) * ppm))
        if sw < 8 or sh < 8:
            return
        x0 = int(rng.uniform(0, max(1, w - sw)))
        y0 = int(rng.uniform(0, max(1, h - sh - 0.5 * ppm)))
        cv2.rectangle(img, (x0, y0), (x0 + sw, y0 + sh), float(rng.uniform(0.05, 0.95)), -1)
        _text_marks(img, rng, x0 + sh, y0, x0 + sw, y0 + sh, ppm)
        c = (x0 + sh // 2, y0 + sh // 2)
        cv2.circle(img, c, max(2, sh // 3), float(rng.uniform(0.0, 1.0)), -1)
        cv2.circle(img, c, max(1, sh // 6), float(rng.uniform(0.0, 1.0)), -1)


def _openings(img: F32, rng: np.random.Generator, ppm: float) -> None:
    """Doors and barred windows with frames, in place."""
    h, w = img.shape
    x = int(rng.uniform(0.2, 0.8) * ppm)
    frame = max(1, round(0.04 * ppm))
    while x < w - 0.6 * ppm:
        if rng.random() < 0.5:  # door from the ground up
            dw, dh = int(rng.uniform(0.8, 1.2) * ppm), int(min(h - 2, 2.0 * ppm))
            top = h - dh
        else:  # window
            dw, dh = int(rng.uniform(0.6, 1.4) * ppm), int(min(h - 2, rng.uniform(0.5, 1.0) * ppm))
            top = int(rng.uniform(0.1, 0.4) * max(1, h - dh))
        dw = min(dw, w - x - 1)
        if dw < 6 or dh < 6:
            break
        shade = float(rng.uniform(0.05, 0.5))
        cv2.rectangle(img, (x, top), (x + dw, top + dh), shade, -1)
        cv2.rectangle(img, (x, top), (x + dw, top + dh), float(rng.uniform(0.6, 0.95)), frame)
        if rng.random() < 0.6:
            for bx in range(x + dw // 4, x + dw, max(3, dw // 4)):
                cv2.line(img, (bx, top), (bx, top + dh), float(rng.uniform(0.5, 0.9)), 1)
        x += dw + int(rng.uniform(0.5, 2.0) * ppm)


def _plain_marks(img: F32, rng: np.random.Generator, ppm: float) -> None:
    """Plain wall: a few faint stains and a vertical panel seam or two, in place."""
    h, w = img.shape
    for _ in range(int(rng.integers(0, 3))):
        x = int(rng.uniform(0, w))
        cv2.line(img, (x, 0), (x, h - 1), float(img[h // 2, min(x, w - 1)] - 0.06), 1)
    for _ in range(int(rng.integers(0, 4))):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        r = max(2, int(rng.uniform(0.1, 0.4) * ppm))
        cv2.circle(img, c, r, float(img[c[1], c[0]] + rng.uniform(-0.08, 0.05)), -1)


def _wall_texture(
    length_m: float, height_m: float, ppm: float, busy_fraction: float, rng: np.random.Generator
) -> U8:
    """Texture of one wall: segments of 1.5-6 m, busy or plain, over a painted background."""
    ht, wt = max(2, math.ceil(height_m * ppm)), max(2, math.ceil(length_m * ppm))
    img = _wall_background((ht, wt), rng, ppm)
    x = 0
    while x < wt:
        seg = min(wt - x, max(4, int(rng.uniform(1.5, 6.0) * ppm)))
        view = img[:, x : x + seg]
        if rng.random() < busy_fraction:
            kind = int(rng.integers(0, 5))
            if kind == 0:
                top = int(rng.uniform(0.0, 0.5) * ht) if rng.random() < 0.4 else 0
                view[top:] = _bricks((ht - top, seg), rng, ppm)
            elif kind == 1:
                _posters(view, rng, ppm)
            elif kind == 2:
                _shelves(view, rng, ppm)
            elif kind == 3:
                _signs(view, rng, ppm)
            else:
                _openings(view, rng, ppm)
        else:
            _plain_marks(view, rng, ppm)
        x += seg
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return to_uint8(np.clip(img, 0.0, 1.0))


def _ground_texture(shape: tuple[int, int], rng: np.random.Generator, ppm: float) -> U8:
    """Concrete and asphalt: patches, slab joints, painted lines, stains, cracks, covers."""
    h, w = shape
    area_m2 = h * w / (ppm * ppm)
    patches = fractal_noise(shape, rng, base_px=12.0 * ppm, octaves=2)
    mottle = fractal_noise(shape, rng, base_px=2.0 * ppm, octaves=4)
    grain = fractal_noise(shape, rng, base_px=2.0, octaves=2)
    img = 0.42 + 0.18 * (patches - 0.5) + 0.12 * (mottle - 0.5) + 0.16 * (grain - 0.5)
    img = np.asarray(img, dtype=np.float32)
    # aggregate: sparse light and dark pebbles of one to two texels
    n_pebbles = int(0.01 * h * w)
    pr, pc = rng.integers(0, h, n_pebbles), rng.integers(0, w, n_pebbles)
    img[pr, pc] += rng.choice(np.array([-0.15, 0.15], np.float32), n_pebbles)
    # concrete slab joints on part of the yard
    slab = int(rng.uniform(2.5, 4.0) * ppm)
    x0, y0 = int(rng.uniform(0, w / 2)), int(rng.uniform(0, h / 2))
    x1, y1 = (
        min(w, x0 + int(rng.uniform(0.3, 0.5) * w)),
        min(h, y0 + int(rng.uniform(0.3, 0.5) * h)),
    )
    for x in range(x0, x1, slab):
        cv2.line(img, (x, y0), (x, y1), 0.25, 1)
    for y in range(y0, y1, slab):
        cv2.line(img, (x0, y), (x1, y), 0.25, 1)
    # painted bay lines and arrows
    line_w = max(1, round(0.1 * ppm))
    for _ in range(max(1, int(area_m2 / 250))):
        bx, by = int(rng.uniform(0, w)), int(rng.uniform(0, h))
        bay = int(rng.uniform(2.4, 3.0) * ppm)
        depth = int(rng.uniform(4.0, 5.5) * ppm)
        vertical = rng.random() < 0.5
        for k in range(int(rng.integers(3, 8))):
            if vertical:
                p, q = (bx + k * bay, by), (bx + k * bay, by + depth)
            else:
                p, q = (bx, by + k * bay), (bx + depth, by + k * bay)
            cv2.line(img, p, q, float(rng.uniform(0.8, 0.95)), line_w)
    for _ in range(max(1, int(area_m2 / 150))):
        c = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        ang = rng.uniform(0, 2 * np.pi)
        u = np.array([np.cos(ang), np.sin(ang)]) * ppm
        v = np.array([-u[1], u[0]])
        tip, tail = c + 0.8 * u, c - 0.8 * u
        pts = np.array([tip, c + 0.2 * u + 0.35 * v, c + 0.2 * u - 0.35 * v], dtype=np.int32)
        cv2.line(img, tuple(int(a) for a in tail), tuple(int(a) for a in c), 0.9, line_w)
        cv2.fillConvexPoly(img, pts, 0.9)
    # oil stains and damp patches
    for _ in range(int(area_m2 / 8)):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        axes = (
            max(1, int(rng.uniform(0.05, 0.5) * ppm)),
            max(1, int(rng.uniform(0.05, 0.4) * ppm)),
        )
        shade = float(np.clip(img[c[1], c[0]] + rng.uniform(-0.2, 0.08), 0, 1))
        cv2.ellipse(img, c, axes, float(rng.uniform(0, 180)), 0, 360, shade, -1)
    # cracks: random walks
    for _ in range(int(area_m2 / 25)):
        p = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        heading = rng.uniform(0, 2 * np.pi)
        pts = [p.copy()]
        for _ in range(int(rng.integers(4, 15))):
            heading += rng.normal(0, 0.5)
            p = p + rng.uniform(0.1, 0.4) * ppm * np.array([np.cos(heading), np.sin(heading)])
            pts.append(p.copy())
        cv2.polylines(img, [np.array(pts, dtype=np.int32)], False, 0.18, 1)
    # manhole and drain covers
    for _ in range(max(1, int(area_m2 / 200))):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        r = max(2, int(0.3 * ppm))
        cv2.circle(img, c, r, 0.22, -1)
        cv2.circle(img, c, max(1, r - 2), 0.32, max(1, r // 6))
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return to_uint8(np.clip(img, 0.0, 1.0))


def _place_obstacles(spec: YardSpec, rng: np.random.Generator) -> list[tuple[str, F64, float]]:
    """(kind, footprint (k, 2) north/east, height) per obstacle, non-overlapping, with
    `obstacle_clearance_m` between each other and from the perimeter."""
    n0, e0 = spec.origin_nav_m
    sn, se = spec.size_m
    clear = spec.obstacle_clearance_m
    placed: list[tuple[str, F64, float]] = []
    centres: list[tuple[F64, float]] = []
    tries = 0
    while len(placed) < spec.n_obstacles:
        tries += 1
        if tries > 300 * spec.n_obstacles + 1000:
            raise ValueError(
                f"yard: cannot place {spec.n_obstacles} obstacles in a {sn:g} m x {se:g} m "
                f"yard with {clear:g} m clearance (placed {len(placed)}); reduce n_obstacles "
                f"or obstacle_clearance_m, or enlarge size_m"
            )
        yaw = rng.uniform(0, np.pi)
        u = np.array([np.cos(yaw), np.sin(yaw)])
        v = np.array([-u[1], u[0]])
        if rng.random() < 0.4:
            kind = "panel"
            half_len = 0.5 * rng.uniform(2.0, 5.0)
            corners = np.stack([-half_len * u, half_len * u])
            height = float(rng.uniform(0.6, 1.0) * spec.wall_height_m)
        else:
            kind = "box"
            a, b = 0.5 * rng.uniform(0.8, 2.5), 0.5 * rng.uniform(0.8, 2.5)
            corners = np.stack([-a * u - b * v, a * u - b * v, a * u + b * v, -a * u + b * v])
            height = float(rng.uniform(0.4, 1.0) * spec.wall_height_m)
        radius = float(np.max(np.linalg.norm(corners, axis=1)))
        lo_n, hi_n = n0 + clear + radius, n0 + sn - clear - radius
        lo_e, hi_e = e0 + clear + radius, e0 + se - clear - radius
        if lo_n > hi_n or lo_e > hi_e:
            continue
        c = np.array([rng.uniform(lo_n, hi_n), rng.uniform(lo_e, hi_e)])
        if any(np.linalg.norm(c - c2) < radius + r2 + clear for c2, r2 in centres):
            continue
        centres.append((c, radius))
        placed.append((kind, corners + c, height))
    return placed


def make_yard(spec: YardSpec, rng: np.random.Generator) -> Yard:
    """Build the yard of `spec`; deterministic given `rng`. Raises `ValueError` for a spec
    that cannot be built (see `YardSpec.check`)."""
    spec.check()
    n0, e0 = (float(v) for v in spec.origin_nav_m)
    sn, se = (float(v) for v in spec.size_m)
    ppm = float(spec.texture_px_per_m)
    H = float(spec.wall_height_m)
    sw, se_, ne, nw = (
        np.array(p) for p in ((n0, e0), (n0, e0 + se), (n0 + sn, e0 + se), (n0 + sn, e0))
    )
    walls: list[Wall] = []
    for p0, p1 in ((sw, se_), (se_, ne), (ne, nw), (nw, sw)):
        length = float(np.linalg.norm(p1 - p0))
        tex = _wall_texture(length, H, ppm, spec.busy_fraction, rng)
        walls.append(Wall(p0, p1, H, tex, ppm, "perimeter"))
    footprints: list[F64] = []
    for kind, poly, height in _place_obstacles(spec, rng):
        footprints.append(poly)
        k = len(poly)
        edges = [(0, 1)] if kind == "panel" else [(j, (j + 1) % k) for j in range(k)]
        for a, b in edges:
            length = float(np.linalg.norm(poly[b] - poly[a]))
            tex = _wall_texture(length, height, ppm, spec.busy_fraction, rng)
            walls.append(Wall(poly[a].copy(), poly[b].copy(), height, tex, ppm, kind))
    gppm = float(spec.ground_px_per_m)
    gsn, gse = spec.ground_size_m
    ground = _ground_texture(
        (max(2, math.ceil(gsn * gppm)), max(2, math.ceil(gse * gppm))), rng, gppm
    )
    return Yard(
        spec=spec, walls=tuple(walls), ground_texture=ground, obstacles_ne=tuple(footprints)
    )


def _build_atlas(yard: Yard) -> _Atlas:
    """Shelf-pack the ground and wall textures (each with a replicated border) into one image."""
    p = _ATLAS_PAD
    tiles = [yard.ground_texture] + [w.texture for w in yard.walls]
    padded = [cv2.copyMakeBorder(t, p, p, p, p, cv2.BORDER_REPLICATE) for t in tiles]
    width = max(_ATLAS_WIDTH_MIN, *(t.shape[1] for t in padded))
    positions: list[tuple[int, int]] = [(0, 0)]
    y, x, shelf_h = padded[0].shape[0], 0, 0
    order = sorted(range(1, len(padded)), key=lambda i: -padded[i].shape[0])
    pos_by_index: dict[int, tuple[int, int]] = {}
    for i in order:
        th, tw = padded[i].shape
        if x + tw > width:
            y, x, shelf_h = y + shelf_h, 0, 0
        pos_by_index[i] = (y, x)
        x += tw
        shelf_h = max(shelf_h, th)
    height = y + shelf_h
    if height > 32000 or width > 32000:
        raise ValueError(
            f"yard: textures need a {width} x {height} atlas (at most 32000 a side); "
            f"reduce texture_px_per_m, ground_px_per_m or n_obstacles"
        )
    positions += [pos_by_index[i] for i in range(1, len(padded))]
    image = np.zeros((height, width), np.float32)
    for (ty, tx), t in zip(positions, padded, strict=True):
        image[ty : ty + t.shape[0], tx : tx + t.shape[1]] = t.astype(np.float32) / 255.0
    rc = np.array([(ty + p, tx + p) for ty, tx in positions], dtype=np.int64)
    return _Atlas(image=image, ground_rc=(int(rc[0, 0]), int(rc[0, 1])), wall_rc=rc[1:])


# --------------------------------------------------------------------------- rendering

_RAYS_CACHE: weakref.WeakKeyDictionary[CameraModel, F64] = weakref.WeakKeyDictionary()


def camera_rays(cam: CameraModel) -> F64:
    """`pixel_rays(cam)`, computed once per camera object (cached while it lives)."""
    rays = _RAYS_CACHE.get(cam)
    if rays is None:
        rays = pixel_rays(cam)
        rays.setflags(write=False)
        _RAYS_CACHE[cam] = rays
    return rays


def _clip_front(p_cam: F64, near: float) -> F64:
    """Clip a planar polygon (k, 3) in the camera frame to z >= near (Sutherland-Hodgman)."""
    out: list[F64] = []
    k = len(p_cam)
    for j in range(k):
        a, b = p_cam[j], p_cam[(j + 1) % k]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            f = (near - a[2]) / (b[2] - a[2])
            out.append(a + f * (b - a))
    return np.array(out).reshape(-1, 3)


def sky_radiance(d_nav: F64 | F32) -> F32:
    """Smooth sky radiance in [0, 1] for (..., 3) nav-frame view directions: brightest at the
    horizon, darker towards the zenith."""
    d = np.asarray(d_nav, dtype=np.float32)
    elev = -d[..., 2] / np.maximum(np.linalg.norm(d, axis=-1), 1e-12)
    return (0.88 - 0.3 * np.sqrt(np.clip(elev, 0.0, 1.0))).astype(np.float32)


def render_yard_view(
    yard: Yard,
    cam: CameraModel,
    T_nav_cam: F64,
    *,
    rays: F64 | None = None,
    want_points: bool = False,
    max_range_m: float = 200.0,
) -> RenderResult:
    """Ray-cast the view of `cam` at pose `T_nav_cam` (4x4, camera optical frame -> nav).

    rays: (H, W, 3) rays (x/z, y/z, 1) of the raw pixels, as from `pixel_rays(cam)`; computed
    (and cached per camera object) when None. Ground hits deeper than `max_range_m` and rays
    that hit nothing show the sky (depth NaN, valid False). See the module docstring."""
    T = np.asarray(T_nav_cam, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_nav_cam must be a finite 4x4 matrix, got shape {T.shape}")
    R, o = T[:3, :3], T[:3, 3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
        raise ValueError("T_nav_cam: the rotation block is not orthonormal")
    if rays is None:
        rays = camera_rays(cam)
    if rays.shape != (cam.height, cam.width, 3):
        raise ValueError(
            f"rays: expected shape ({cam.height}, {cam.width}, 3) for a "
            f"{cam.width}x{cam.height} camera, got {rays.shape}"
        )
    if not max_range_m > 0:
        raise ValueError(f"max_range_m must be positive, got {max_range_m:g}")
    x = np.ascontiguousarray(rays[..., 0], dtype=np.float32)
    y = np.ascontiguousarray(rays[..., 1], dtype=np.float32)
    atlas = yard._atlas
    spec = yard.spec

    # Ray direction in nav for the camera ray (x, y, 1): d = R[:, 0] x + R[:, 1] y + R[:, 2].
    def dot(r: F64) -> F32:
        return float(r[0]) * x + float(r[1]) * y + float(r[2])

    dn, de, dz = dot(R[0]), dot(R[1]), dot(R[2])
    # Ground plane z = 0: o_z + t dz = 0.
    with np.errstate(divide="ignore", invalid="ignore"):
        t_g = np.float32(-o[2]) / dz
    ground = (t_g > NEAR_M) & (t_g <= max_range_m)
    best = np.where(ground, t_g, np.float32(np.inf)).astype(np.float32)
    t0 = np.where(ground, t_g, np.float32(0.0))
    gppm = float(spec.ground_px_per_m)
    gh, gw = yard.ground_texture.shape
    n0, e0 = spec.ground_origin_nav_m
    map_y = np.clip((float(o[0]) - n0 + t0 * dn) * gppm - 0.5, -0.5, gh - 0.5)
    map_x = np.clip((float(o[1]) - e0 + t0 * de) * gppm - 0.5, -0.5, gw - 0.5)
    map_y += np.float32(atlas.ground_rc[0])
    map_x += np.float32(atlas.ground_rc[1])
    hit_any = ground.copy()

    # Per-column and per-row range of the rays' normalised coordinates, for wall culling.
    col_lo, col_hi = x.min(axis=0), x.max(axis=0)
    row_lo, row_hi = y.min(axis=1), y.max(axis=1)
    for i, wall in enumerate(yard.walls):
        u = wall.direction_ne
        L, Hw, ppm = wall.length_m, wall.height_m, wall.px_per_m
        corners = np.array(
            [
                [*wall.p0_ne, 0.0],
                [*wall.p1_ne, 0.0],
                [*wall.p1_ne, -Hw],
                [*wall.p0_ne, -Hw],
            ]
        )
        poly = _clip_front((corners - o) @ R, NEAR_M)
        if len(poly) < 3:
            continue
        px, py = poly[:, 0] / poly[:, 2], poly[:, 1] / poly[:, 2]
        cols = np.flatnonzero((col_hi >= px.min()) & (col_lo <= px.max()))
        rows = np.flatnonzero((row_hi >= py.min()) & (row_lo <= py.max()))
        if cols.size == 0 or rows.size == 0:
            continue
        win = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        xs, ys = x[win], y[win]
        # Vertical plane through p0 with horizontal normal m: m . (o_h + t d_h - p0) = 0.
        m = np.array([-u[1], u[0], 0.0])
        a = R.T @ m  # m . d = a . (x, y, 1)
        b = R.T @ np.array([u[0], u[1], 0.0])  # u . d
        num = float(m[:2] @ (wall.p0_ne - o[:2]))
        s0 = float(u @ (o[:2] - wall.p0_ne))
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / (float(a[0]) * xs + float(a[1]) * ys + float(a[2]))
        bw = best[win]
        hit = (t > NEAR_M) & (t < bw) & (t <= max_range_m)
        s = s0 + t * (float(b[0]) * xs + float(b[1]) * ys + float(b[2]))
        z = float(o[2]) + t * dz[win]
        hit &= (s >= 0) & (s <= L) & (z >= -Hw) & (z <= 0)
        if not hit.any():
            continue
        ay, ax = (float(v) for v in atlas.wall_rc[i])
        np.copyto(bw, t, where=hit)
        np.copyto(map_x[win], s * ppm + (ax - 0.5), where=hit)
        np.copyto(map_y[win], (z + Hw) * ppm + (ay - 0.5), where=hit)
        hit_any[win] |= hit

    radiance = cv2.remap(
        atlas.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    valid = hit_any
    if not valid.all():
        sky = ~valid
        d_sky = np.stack([dn[sky], de[sky], dz[sky]], axis=-1)
        radiance[sky] = sky_radiance(d_sky)
    depth = np.where(valid, best, np.float32(np.nan)).astype(np.float32)
    p_nav = None
    if want_points:
        p_nav = np.stack(
            [float(o[0]) + depth * dn, float(o[1]) + depth * de, float(o[2]) + depth * dz],
            axis=-1,
        ).astype(np.float32)
    return RenderResult(radiance=radiance, depth_m=depth, p_nav_m=p_nav, valid=valid)
