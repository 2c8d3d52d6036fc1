"""The UAV world: a textured height field with real relief, and its ray-cast camera views.

World
-----
A rectangle of `size_m` = (north extent, east extent) whose south-west corner is at
`origin_nav_m` = (n0, e0) in the nav frame (NED). Two rasters describe it:

- `elevation_m` (Hh, Wh), up-positive: node (i, j) lies at n = n0 + i * height_res_m,
  e = e0 + j * height_res_m (row <-> north, col <-> east, both increasing away from the origin).
  The surface is the *bilinear* interpolant of these nodes, at nav z = -elevation; every query
  (`elevation_at`, `surface_nav`, the renderer) uses that same interpolant, so the rendered
  geometry and the ground truth agree to the solver's tolerance, not to the grid spacing.
- `texture` (Ht, Wt) uint8 orthophoto and `urban_weight` (Ht, Wt) float32: texel (r, c)
  covers n in [n0 + r / px, n0 + (r + 1) / px), e in [e0 + c / px, e0 + (c + 1) / px) with
  px = texture_px_per_m; its value is the radiance at the texel's centre and `texture_at`
  interpolates bilinearly between centres (OpenCV's convention, shifted by the origin).

Memory: the texture costs 5 bytes per texel (uint8 + float32 weight): the default
800 m x 800 m at 4 px/m is 3200 x 3200 texels = 50 MiB resident, plus the renderer's
caches (per-cell coefficients, mip levels) built on first use (their measured size and the
peak while building: BENCHMARKS.md, "Figures from docstrings"). 4 px/m (0.25 m texels)
matches the ground sample distance of a 450 px focal length from ~110 m; lower flights see
a blurrier (upsampled) ground, higher ones are rendered from a downsampled level (see
below). Specs above `MAX_TEXELS` are refused.

Ray casting (`render_terrain_view`)
----------------------------------
Each pixel's ray in the camera frame is r = (x/z, y/z, 1) (`pixel_rays`, which undoes the lens
distortion of the raw image), so the point at parameter s along it is p_cam = s * r and s *is*
the depth. In nav: p(s) = c + s * d with d = R_nav_cam r. The first intersection with the
surface is the root of

    g(s) = c_z + s d_z + E(c_n + s d_n, c_e + s d_e)        (E = bilinear elevation, up)

g < 0 above the ground and g' = d_z + grad(E) . (d_n, d_e). Assumption: g' > 0 along the
ray, i.e. |grad E| * tan(angle of the ray from the vertical) < 1 (with the default terrain,
max slope ~0.5, any ray within ~60 deg of nadir qualifies), which makes the root unique
(no terrain hides other terrain) and g monotonic, so the iteration below converges to it.
Near-nadir UAV views satisfy it; views that break it (low oblique views of steep hills) may
converge on a hidden surface point or not converge; pixels that have not converged are
marked invalid. `Terrain.max_slope` gives |grad E| for checking a planned view.

Method. In one cell of the grid E = a + b fc + c fr + d fr fc (fr, fc: position in the cell
along north and east), so along a ray g is a quadratic in s, whose root nearest to the
current depth is solved in closed form; the result is *exact* (to float32 rounding, ~1e-5 m)
when it lies in the cell that was solved, which is checked. (1) Solve a coarse grid of rays
(8 x 8-pixel block averages) from the plane of mean elevation, iterating cell by cell;
(2) upsample those depths bilinearly as every pixel's initial guess (a few cm off);
(3) one exact pass per pixel (one 16-byte gather of the cell's coefficients); the few (<~1 %)
pixels whose root lies in another cell than their guess take more passes (at most 30, clamped
between the planes of highest and lowest elevation, Newton steps where the quadratic has no
real root); pixels still without an exact root are invalid.
Radiance is then the texture sampled at the hit with `cv2.remap` (bilinear; OpenCV quantises
the sampling position to 1/32 texel) from mip level l = floor(log2(footprint / 1.25)), where
footprint is the ground size of a pixel in level-0 texels at the median depth (one level per
image). That rule picks the level closest to a 4x4-supersampled reference render at every
altitude tried (it switches at footprints of ~2.5, 5 and 10 texels): distant views neither
alias nor blur more than needed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.projection import pixel_rays
from cvslam_cli.records.arrays import F32, F64
from cvslam_cli.sim.render import RenderResult
from cvslam_cli.sim.texture import busy_texture, fractal_noise, smooth_texture, to_uint8

MAX_TEXELS = 100_000_000
"""Largest orthophoto `make_terrain` builds (0.5 GB resident, several GB while building)."""

_COARSE_BLOCK_PX = 8
_COARSE_PASSES = 20
_REFINE_PASSES = 30
_MIP_FOOTPRINT_TEXELS = 1.25  # level l once a pixel spans 1.25 * 2**l texels (see docstring)
_CELL_EPS = 1e-4  # a root may overshoot its cell by this fraction (float32 rounding)
_MIN_DOWNWARD = 1e-6
_SUN_AZIMUTH_RAD = math.radians(315.0)  # from the north-west, as cartographic hillshades
_SUN_ELEVATION_RAD = math.radians(45.0)


@dataclass(frozen=True)
class TerrainSpec:
    """What world to build. Lengths in metres.

    size_m: (north extent, east extent). origin_nav_m: (north, east) of the south-west corner.
    texture_px_per_m: orthophoto resolution (memory: 5 bytes per texel, see module docstring).
    height_res_m: spacing of the elevation grid. relief_m: peak-to-peak elevation (0 = flat).
    relief_scale_m: size of the largest hills. urban_fraction: share of the area that is busy
    (urban) rather than smooth (desert, sea). region_scale_m: size of those regions.
    hillshade: strength of the slope shading baked into the orthophoto (0 = none).
    """

    size_m: tuple[float, float] = (800.0, 800.0)
    origin_nav_m: tuple[float, float] = (-400.0, -400.0)
    texture_px_per_m: float = 4.0
    height_res_m: float = 2.0
    relief_m: float = 40.0
    relief_scale_m: float = 150.0
    urban_fraction: float = 0.5
    region_scale_m: float = 250.0
    hillshade: float = 0.3

    def __post_init__(self) -> None:
        for name in ("size_m", "origin_nav_m"):
            value = getattr(self, name)
            try:
                pair = tuple(float(v) for v in value)
            except (TypeError, ValueError):
                pair = ()
            if len(pair) != 2 or not all(math.isfinite(v) for v in pair):
                raise ValueError(
                    f"TerrainSpec.{name} must be two finite numbers (north, east), got {value!r}"
                )
            object.__setattr__(self, name, pair)  # lists from a config become tuples
        if min(self.size_m) <= 0:
            raise ValueError(f"TerrainSpec.size_m must be positive, got {self.size_m!r}")
        for name in ("texture_px_per_m", "height_res_m", "relief_scale_m", "region_scale_m"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"TerrainSpec.{name} must be a positive number, got {value!r}")
        for name in ("relief_m", "hillshade"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"TerrainSpec.{name} must be >= 0, got {value!r}")
        if not 0.0 <= float(self.urban_fraction) <= 1.0:
            raise ValueError(
                f"TerrainSpec.urban_fraction must lie in [0, 1], got {self.urban_fraction!r}"
            )
        if self.height_res_m > min(self.size_m):
            raise ValueError(
                f"TerrainSpec.height_res_m ({self.height_res_m:g} m) exceeds the terrain's "
                f"smaller extent ({min(self.size_m):g} m)"
            )
        ht, wt = self.texture_shape
        if ht * wt > MAX_TEXELS:
            raise ValueError(
                f"TerrainSpec: the orthophoto would be {ht} x {wt} texels "
                f"({ht * wt / 1e6:.0f} M, 5 bytes each); at most {MAX_TEXELS / 1e6:.0f} M "
                "are allowed: lower texture_px_per_m or size_m"
            )

    @property
    def texture_shape(self) -> tuple[int, int]:
        """(Ht, Wt): rows along north, columns along east."""
        px = float(self.texture_px_per_m)
        return (
            max(1, math.ceil(self.size_m[0] * px - 1e-9)),
            max(1, math.ceil(self.size_m[1] * px - 1e-9)),
        )

    @property
    def elevation_shape(self) -> tuple[int, int]:
        """(Hh, Wh): nodes along north and east (the grid covers at least size_m)."""
        res = float(self.height_res_m)
        return (
            math.ceil(self.size_m[0] / res - 1e-9) + 1,
            math.ceil(self.size_m[1] / res - 1e-9) + 1,
        )


@dataclass(frozen=True, eq=False)
class Terrain:
    """A built world (see the module docstring for the raster conventions).

    elevation_m: (Hh, Wh) float64, up-positive; the surface is at nav z = -elevation.
    texture: (Ht, Wt) uint8 orthophoto (radiance * 255).
    urban_weight: (Ht, Wt) float32 in [0, 1]: 0 = smooth region, 1 = busy (urban).
    """

    spec: TerrainSpec
    elevation_m: F64 = field(repr=False)
    texture: NDArray[np.uint8] = field(repr=False)
    urban_weight: F32 = field(repr=False)

    def __post_init__(self) -> None:
        if self.elevation_m.shape != self.spec.elevation_shape:
            raise ValueError(
                f"Terrain.elevation_m has shape {self.elevation_m.shape}, the spec needs "
                f"{self.spec.elevation_shape}"
            )
        for name, dtype in (("texture", np.uint8), ("urban_weight", np.float32)):
            arr = getattr(self, name)
            if arr.shape != self.spec.texture_shape or arr.dtype != dtype:
                raise ValueError(
                    f"Terrain.{name} is {arr.dtype} {arr.shape}, the spec needs "
                    f"{np.dtype(dtype)} {self.spec.texture_shape}"
                )
        if not np.all(np.isfinite(self.elevation_m)):
            raise ValueError("Terrain.elevation_m holds non-finite values")

    # -- queries --------------------------------------------------------------------------

    @property
    def bounds_nav_m(self) -> tuple[float, float, float, float]:
        """(n_min, n_max, e_min, e_max) of the terrain rectangle."""
        n0, e0 = self.spec.origin_nav_m
        return (n0, n0 + self.spec.size_m[0], e0, e0 + self.spec.size_m[1])

    @cached_property
    def max_slope(self) -> float:
        """Largest |grad E| of the bilinear surface (rise over run)."""
        E, res = self.elevation_m, self.spec.height_res_m
        dn, de = np.abs(np.diff(E, axis=0)) / res, np.abs(np.diff(E, axis=1)) / res
        # in a cell the gradient is (interpolated dn, interpolated de): bounded by edge values
        return float(np.hypot(np.maximum(dn[:, :-1], dn[:, 1:]), np.maximum(de[:-1], de[1:])).max())

    @property
    def nbytes(self) -> int:
        return int(self.elevation_m.nbytes + self.texture.nbytes + self.urban_weight.nbytes)

    def contains(self, n_m: F64 | float, e_m: F64 | float) -> NDArray[np.bool_]:
        """Whether (n, e) lies on the terrain rectangle (borders included)."""
        n_min, n_max, e_min, e_max = self.bounds_nav_m
        n, e = np.asarray(n_m, dtype=float), np.asarray(e_m, dtype=float)
        return (n >= n_min) & (n <= n_max) & (e >= e_min) & (e <= e_max)

    def elevation_at(self, n_m: F64 | float, e_m: F64 | float) -> F64:
        """Bilinear elevation (up, metres) at nav (n, e); clamped to the edge values outside."""
        n0, e0 = self.spec.origin_nav_m
        res = self.spec.height_res_m
        n, e = np.broadcast_arrays(np.asarray(n_m, dtype=float), np.asarray(e_m, dtype=float))
        return _bilinear(self.elevation_m, (n - n0) / res, (e - e0) / res)

    def surface_nav(self, n_m: F64 | float, e_m: F64 | float) -> F64:
        """(N, 3) nav-frame points (n, e, -elevation) on the surface."""
        n, e = np.broadcast_arrays(np.asarray(n_m, dtype=float), np.asarray(e_m, dtype=float))
        n, e = n.ravel(), e.ravel()
        return np.column_stack([n, e, -self.elevation_at(n, e)])

    def texture_at(self, n_m: F64 | float, e_m: F64 | float) -> F64:
        """Bilinear orthophoto radiance in [0, 1] at nav (n, e) (level 0, edge-clamped)."""
        n0, e0 = self.spec.origin_nav_m
        px = self.spec.texture_px_per_m
        n, e = np.broadcast_arrays(np.asarray(n_m, dtype=float), np.asarray(e_m, dtype=float))
        return _bilinear(self.texture, (n - n0) * px - 0.5, (e - e0) * px - 0.5) / 255.0

    # -- renderer support -----------------------------------------------------------------

    @cached_property
    def _cells(self) -> F32:
        """(Hh-1, Wh-1, 4) float32 bilinear coefficients per cell: E = a + b fc + c fr + d fr fc
        with fr, fc in [0, 1) the position inside the cell along north and east."""
        E = self.elevation_m
        e00, e01, e10, e11 = E[:-1, :-1], E[:-1, 1:], E[1:, :-1], E[1:, 1:]
        cells = np.stack([e00, e01 - e00, e10 - e00, e11 - e10 - e01 + e00], axis=-1)
        return np.ascontiguousarray(cells, dtype=np.float32)

    @cached_property
    def _texture_levels(self) -> tuple[NDArray[np.uint8], ...]:
        """Mip levels: level l has texels 2**l times larger, centres aligned with the
        `texture` convention (2x2 box averages, edge-padded to even sizes)."""
        levels = [self.texture]
        while len(levels) < 6 and min(levels[-1].shape) >= 32:
            t = levels[-1]
            h, w = t.shape
            t = cv2.copyMakeBorder(t, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)
            levels.append(cv2.resize(t, (t.shape[1] // 2, t.shape[0] // 2), cv2.INTER_AREA))
        return tuple(levels)


def _bilinear(grid: NDArray[np.generic], r: F64, c: F64) -> F64:
    """Exact float64 bilinear interpolation of `grid` at fractional (row, col), edge-clamped."""
    h, w = grid.shape
    r = np.clip(r, 0.0, h - 1.0)
    c = np.clip(c, 0.0, w - 1.0)
    i = np.minimum(np.floor(r).astype(np.intp), max(h - 2, 0))
    j = np.minimum(np.floor(c).astype(np.intp), max(w - 2, 0))
    fr, fc = r - i, c - j
    i1, j1 = np.minimum(i + 1, h - 1), np.minimum(j + 1, w - 1)
    g00, g01 = grid[i, j].astype(np.float64), grid[i, j1].astype(np.float64)
    g10, g11 = grid[i1, j].astype(np.float64), grid[i1, j1].astype(np.float64)
    top = g00 + (g01 - g00) * fc
    bottom = g10 + (g11 - g10) * fc
    return top + (bottom - top) * fr


def make_terrain(spec: TerrainSpec, rng: np.random.Generator) -> Terrain:
    """Build the world of `spec`, deterministically given `rng`.

    Relief: 4-octave fractal noise (largest cells `relief_scale_m`, persistence 0.4) scaled
    to exactly [0, relief_m]. Regions: 3-octave fractal noise at 1 m resolution, thresholded
    at its (1 - urban_fraction) quantile with a soft edge (~10 m), so that busy texture covers
    `urban_fraction` of the area in large blobs. Orthophoto: smooth and busy textures blended
    by that weight, times a hillshade (sun from the north-west, 45 deg high).
    """
    hh, wh = spec.elevation_shape
    ht, wt = spec.texture_shape
    px = float(spec.texture_px_per_m)

    noise = fractal_noise(
        (hh, wh), rng, base_px=spec.relief_scale_m / spec.height_res_m, octaves=4, persistence=0.4
    ).astype(np.float64)
    lo, hi = float(noise.min()), float(noise.max())
    elevation = spec.relief_m * (noise - lo) / max(hi - lo, 1e-12)

    # regions, at ~1 m resolution then upsampled
    rh, rw = max(2, math.ceil(spec.size_m[0])), max(2, math.ceil(spec.size_m[1]))
    region = fractal_noise((rh, rw), rng, base_px=spec.region_scale_m, octaves=3)
    if spec.urban_fraction <= 0.0:
        weight_small = np.zeros_like(region)
    elif spec.urban_fraction >= 1.0:
        weight_small = np.ones_like(region)
    else:
        threshold = float(np.quantile(region, 1.0 - spec.urban_fraction))
        x = np.clip((region - threshold) / 0.05 + 0.5, 0.0, 1.0)
        weight_small = x * x * (3.0 - 2.0 * x)  # smoothstep
    weight = cv2.resize(weight_small.astype(np.float32), (wt, ht), interpolation=cv2.INTER_LINEAR)

    if spec.urban_fraction < 1.0:
        image = smooth_texture((ht, wt), rng, px_per_m=px)
        if spec.urban_fraction > 0.0:
            busy = busy_texture((ht, wt), rng, px_per_m=px)
            busy -= image
            busy *= weight
            image += busy
            del busy
    else:
        image = busy_texture((ht, wt), rng, px_per_m=px)

    if spec.hillshade > 0 and spec.relief_m > 0:
        shade = _hillshade(elevation, spec.height_res_m)
        factor = 1.0 + spec.hillshade * (shade - 1.0)
        # texel centres in elevation-grid coordinates: ((r + 0.5) / px) / res
        scale = 1.0 / (px * spec.height_res_m)
        map_r = ((np.arange(ht, dtype=np.float32) + 0.5) * scale)[:, None]
        map_c = ((np.arange(wt, dtype=np.float32) + 0.5) * scale)[None, :]
        # separable linear interpolation via two 1-D resizes would misalign; remap is exact
        factor_tex = cv2.remap(
            factor.astype(np.float32),
            np.broadcast_to(map_c, (ht, wt)).astype(np.float32),
            np.broadcast_to(map_r, (ht, wt)).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        image *= factor_tex
        del factor_tex
    np.clip(image, 0.0, 1.0, out=image)
    return Terrain(spec=spec, elevation_m=elevation, texture=to_uint8(image), urban_weight=weight)


def _hillshade(elevation_m: F64, res_m: float) -> F64:
    """Lambertian shading of the relief relative to flat ground (1 = flat, 0 = in shadow)."""
    dn, de = np.gradient(elevation_m, res_m)
    # up-positive surface normal in (north, east, up): (-dE/dn, -dE/de, 1) / norm
    norm = np.sqrt(dn * dn + de * de + 1.0)
    sun = np.array(
        [
            math.cos(_SUN_ELEVATION_RAD) * math.cos(_SUN_AZIMUTH_RAD),
            math.cos(_SUN_ELEVATION_RAD) * math.sin(_SUN_AZIMUTH_RAD),
            math.sin(_SUN_ELEVATION_RAD),
        ]
    )
    cos_incidence = (-dn * sun[0] - de * sun[1] + sun[2]) / norm
    return np.maximum(cos_incidence, 0.0) / sun[2]


# -- rendering ------------------------------------------------------------------------------


@dataclass
class _Rays32:
    """N rays, flattened float32, in elevation-grid units: row(s) = r0 + s * dr (north, in
    cells), col(s) = c0 + s * dc (east), nav z(s) = cz + s * dz (down, metres)."""

    r0: float
    c0: float
    cz: float
    dr: F32
    dc: F32
    dz: F32

    def subset(self, sel: NDArray[np.intp]) -> _Rays32:
        return _Rays32(self.r0, self.c0, self.cz, self.dr[sel], self.dc[sel], self.dz[sel])


@dataclass
class _Pass:
    """Result of one solver pass from depths s: the new depths, their grid position and
    whether the new depth is an exact root (it lies in the cell whose polynomial was solved)."""

    s: F32
    r: F32
    c: F32
    exact: NDArray[np.bool_]


def _solve_pass(terrain: Terrain, ray: _Rays32, s: F32, *, newton_fallback: bool) -> _Pass:
    """Solve g = 0 (module docstring) exactly inside the cell where each ray is at depth s.

    With fr, fc the position in the cell at s and Δ = s' - s, the bilinear patch makes g a
    quadratic g + g' Δ + A Δ² (A = d dr dc); its root nearest to s is Δ = -2 g / (g' +
    sqrt(g'² - 4 A g)) (the stable form of the quadratic formula; Newton's step as A -> 0).
    The new depth is exact iff its position lies in that same cell. Positions outside the grid
    use the nearest edge cell's polynomial, extended (continuous; such pixels are invalid).
    With `newton_fallback`, rays without a real root take a Newton step instead."""
    cells = terrain._cells
    hc, wc = cells.shape[:2]
    r = ray.dr * s
    r += np.float32(ray.r0)
    c = ray.dc * s
    c += np.float32(ray.c0)
    fi = np.floor(np.clip(r, 0, np.float32(hc - 1)))
    fj = np.floor(np.clip(c, 0, np.float32(wc - 1)))
    fr = r - fi
    fc = c - fj
    idx = fi.astype(np.int32)
    idx *= wc
    idx += fj.astype(np.int32)
    k = np.take(cells.reshape(-1, 4), idx, axis=0)
    a, b, cq, d = k[:, 0], k[:, 1], k[:, 2], k[:, 3]
    dE_dc = d * fr
    dE_dc += b
    dE_dr = d * fc
    dE_dr += cq
    g = dE_dc * fc  # E = a + fc (b + d fr) + cq fr
    g += a
    g += cq * fr
    g += ray.dz * s
    g += np.float32(ray.cz)
    gp = dE_dc * ray.dc
    gp += dE_dr * ray.dr
    gp += ray.dz
    A = d * ray.dr
    A *= ray.dc
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        A *= g
        A *= np.float32(-4.0)
        A += gp * gp  # discriminant
        np.sqrt(A, out=A)
        A += gp
        step = np.divide(g, A, out=A)
        step *= np.float32(-2.0)
        if newton_fallback:
            bad = ~np.isfinite(step)
            if bad.any():
                step[bad] = -g[bad] / gp[bad]
        s_new = s + step
        r += ray.dr * step
        c += ray.dc * step
        fr = r - fi  # position of the new depth relative to the solved cell
        fc = c - fj
    lo, hi = np.float32(-_CELL_EPS), np.float32(1.0 + _CELL_EPS)
    exact = (fr >= lo) & (fr <= hi)
    exact &= fc >= lo
    exact &= fc <= hi
    return _Pass(s_new, r, c, exact)


def _solve_iteratively(
    terrain: Terrain, ray: _Rays32, s: F32, max_passes: int, z_top: float, z_bottom: float
) -> _Pass:
    """Passes until every ray has its exact root, each clamped to the slab of depths between
    the planes of maximum and minimum elevation (where the first intersection must lie);
    rays whose whole slab lies off the grid are given up at once."""
    s_top = np.maximum((z_top - ray.cz) / ray.dz, 0.0).astype(np.float32)
    s_bottom = np.maximum((z_bottom - ray.cz) / ray.dz, 0.0).astype(np.float32)
    hc, wc = terrain._cells.shape[:2]
    r_top, r_bottom = ray.r0 + s_top * ray.dr, ray.r0 + s_bottom * ray.dr
    c_top, c_bottom = ray.c0 + s_top * ray.dc, ray.c0 + s_bottom * ray.dc
    off_grid = (
        ((r_top < 0) & (r_bottom < 0))
        | ((r_top > hc) & (r_bottom > hc))
        | ((c_top < 0) & (c_bottom < 0))
        | ((c_top > wc) & (c_bottom > wc))
    )
    s = np.where(np.isfinite(s), s, s_top).astype(np.float32)
    out = _Pass(s, ray.r0 + s * ray.dr, ray.c0 + s * ray.dc, np.zeros(s.shape, bool))
    todo = np.flatnonzero(~off_grid)
    for _ in range(max_passes):
        if todo.size == 0:
            break
        sub = ray.subset(todo)
        s_sub = np.clip(out.s[todo], s_top[todo], s_bottom[todo])
        p = _solve_pass(terrain, sub, s_sub, newton_fallback=True)
        keep = np.isfinite(p.s)  # rays that lost their way are given up (stay not exact)
        upd = todo[keep]
        out.s[upd], out.r[upd], out.c[upd], out.exact[upd] = (
            p.s[keep],
            p.r[keep],
            p.c[keep],
            p.exact[keep],
        )
        todo = todo[keep & ~p.exact]
    return out


def render_terrain_view(
    terrain: Terrain,
    cam: CameraModel,
    T_nav_cam: F64,
    *,
    rays: F64 | None = None,
    want_points: bool = False,
    texture_level: int | None = None,
) -> RenderResult:
    """Ray-cast the raw (distorted) image of `cam` at pose `T_nav_cam` (4x4, camera optical
    frame -> nav) over `terrain` (method and assumptions in the module docstring).

    `rays` is `pixel_rays(cam)` ((H, W, 3), z = 1), which callers should compute once per
    camera and pass in. Invalid pixels (ray not pointing down, hit outside the terrain
    rectangle, solver not converged) have radiance 0 and depth NaN. `texture_level` forces a
    mip level (0 = full resolution) instead of the one chosen from the median depth.
    """
    T = np.asarray(T_nav_cam, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_nav_cam must be a finite 4x4 matrix, got shape {T.shape}")
    h, w = cam.height, cam.width
    if rays is None:
        rays = pixel_rays(cam)
    rays = np.asarray(rays)
    if rays.shape != (h, w, 3):
        raise ValueError(
            f"rays has shape {rays.shape}, expected ({h}, {w}, 3) for a {w}x{h} camera"
        )
    spec = terrain.spec
    res, px = spec.height_res_m, spec.texture_px_per_m
    n0, e0 = spec.origin_nav_m
    c_nav = T[:3, 3]
    r0, c0, cz = (c_nav[0] - n0) / res, (c_nav[1] - e0) / res, float(c_nav[2])
    E = terrain.elevation_m
    z_top, z_bottom = -float(E.max()), -float(E.min())
    # rows of M: d_row, d_col (grid units per unit of s), d_z (metres per unit of s)
    M = np.vstack([T[0, :3] / res, T[1, :3] / res, T[2, :3]])

    # (1) coarse solve on block-averaged rays, from the plane of mean elevation
    kb = _COARSE_BLOCK_PX
    cw, ch = max(1, w // kb), max(1, h // kb)
    coarse_rays = cv2.resize(rays, (cw, ch), interpolation=cv2.INTER_AREA).reshape(-1, 3)
    dc3 = (coarse_rays @ M.T).astype(np.float32)
    down_c = dc3[:, 2] > _MIN_DOWNWARD
    coarse = _Rays32(r0, c0, cz, dc3[:, 0], dc3[:, 1], np.where(down_c, dc3[:, 2], 1.0))
    s_coarse = np.full(cw * ch, max(0.5 * (z_top + z_bottom) - cz, 0.0), np.float32)
    s_coarse /= coarse.dz
    sol = _solve_iteratively(terrain, coarse, s_coarse, _COARSE_PASSES, z_top, z_bottom)
    s_coarse = np.where(down_c & np.isfinite(sol.s), sol.s, np.float32(max(-cz, 1.0)))

    # (2) initial guess of every pixel: the coarse depths, bilinearly upsampled
    s = cv2.resize(s_coarse.reshape(ch, cw), (w, h), interpolation=cv2.INTER_LINEAR).ravel()

    # (3) one exact pass at full resolution; the few rays it leaves unsolved are iterated
    # cv2.transform (SIMD) rather than a BLAS product, whose threads stall on a busy machine
    d3 = cv2.transform(rays.astype(np.float32, copy=False), M.astype(np.float32))
    dr, dc, dz = np.moveaxis(d3.reshape(-1, 3), 1, 0).copy()  # (3, N): contiguous rows
    down = dz > _MIN_DOWNWARD
    all_down = bool(down.all())
    if not all_down:
        dz = np.where(down, dz, np.float32(1.0))
    ray = _Rays32(r0, c0, cz, dr, dc, dz)
    sol = _solve_pass(terrain, ray, s, newton_fallback=False)
    if not sol.exact.all():
        sel = np.flatnonzero(~sol.exact)
        more = _solve_iteratively(terrain, ray.subset(sel), s[sel], _REFINE_PASSES, z_top, z_bottom)
        sol.s[sel], sol.r[sel], sol.c[sel], sol.exact[sel] = more.s, more.r, more.c, more.exact
    s, r, c = sol.s, sol.r, sol.c

    valid = sol.exact & (s > 0)
    if not all_down:
        valid &= down
    n_max, e_max = np.float32(spec.size_m[0] / res), np.float32(spec.size_m[1] / res)
    valid &= (r >= 0) & (r <= n_max) & (c >= 0) & (c <= e_max)
    if bool((rays[..., 2] == 1.0).all()):  # as from pixel_rays: s is the depth
        depth = s.copy()
    else:
        depth = s * rays[..., 2].astype(np.float32).ravel()

    # radiance from the mip level that suits the median ground footprint of a pixel
    footprint_texels = float(np.median(s_coarse)) / (0.5 * (cam.fx + cam.fy)) * px
    levels = terrain._texture_levels
    if texture_level is None:
        level = math.floor(math.log2(max(footprint_texels / _MIP_FOOTPRINT_TEXELS, 1.0)))
    else:
        level = int(texture_level)
    level = min(len(levels) - 1, max(0, level))
    scale = np.float32(res * px / 2**level)
    map_x = c * scale
    map_x -= np.float32(0.5)
    map_y = r * scale
    map_y -= np.float32(0.5)
    sample = cv2.remap(
        levels[level],
        map_x.reshape(h, w),
        map_y.reshape(h, w),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    radiance = sample.astype(np.float32).ravel()
    radiance *= np.float32(1.0 / 255.0)

    all_valid = bool(valid.all())
    if not all_valid:
        invalid = ~valid
        np.copyto(radiance, np.float32(0.0), where=invalid)
        np.copyto(depth, np.float32(np.nan), where=invalid)
    points = None
    if want_points:
        p_n = r.astype(np.float64) * res + n0
        p_e = c.astype(np.float64) * res + e0
        p_z = dz.astype(np.float64) * s + cz
        points = np.stack([p_n, p_e, p_z], axis=1).astype(np.float32).reshape(h, w, 3)
        if not all_valid:
            points[~valid.reshape(h, w)] = np.nan
    return RenderResult(
        radiance=radiance.reshape(h, w),
        depth_m=depth.reshape(h, w),
        p_nav_m=points,
        valid=valid.reshape(h, w),
    )
