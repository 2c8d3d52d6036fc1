"""How well a mosaic matches a reference orthophoto of the same ground (the simulator's true
texture): a global translation search, and the same search per tile for local misalignment.

Shift convention: (dr, dc) such that mosaic[r, c] ~ reference[r + dr, c + dc]; a mosaic built
from exact poses on the exact ground has (0, 0). Scores are zero-mean normalised
cross-correlations over the mosaic's covered pixels (`cv2.matchTemplate`, TM_CCOEFF_NORMED
with the mask), so a gain or offset between the images does not matter. Sub-pixel shifts
come from a parabola through the peak and its neighbours in each direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.mosaic.project import CanvasGrid
from cvslam_cli.records.arrays import F32


def resample_reference(
    texture: NDArray, origin_ne: tuple[float, float], px_per_m: float, grid: CanvasGrid
) -> tuple[F32, NDArray[np.bool_]]:
    """The reference raster (texel (i, j) centred at n = n0 + (i + 0.5) / px, e = e0 +
    (j + 0.5) / px) sampled at the canvas pixel centres of `grid`, and where it exists."""
    rows, cols = grid.shape
    n = grid.n_max - (np.arange(rows) + 0.5) * grid.gsd_m
    e = grid.e_min + (np.arange(cols) + 0.5) * grid.gsd_m
    ti = ((n - origin_ne[0]) * px_per_m - 0.5).astype(np.float32)
    tj = ((e - origin_ne[1]) * px_per_m - 0.5).astype(np.float32)
    map_i, map_j = (
        np.broadcast_to(ti[:, None], grid.shape),
        np.broadcast_to(tj[None, :], grid.shape),
    )
    src = texture.astype(np.float32)
    if grid.gsd_m * px_per_m >= 2.0:  # reduce first when the canvas is much coarser
        k = int(np.floor(np.log2(grid.gsd_m * px_per_m)))
        for _ in range(k):
            src = cv2.pyrDown(src)
        s = 1.0 / (1 << k)
        map_i, map_j = (map_i + 0.5) * s - 0.5, (map_j + 0.5) * s - 0.5
    out = cv2.remap(
        src,
        np.ascontiguousarray(map_j, np.float32),
        np.ascontiguousarray(map_i, np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    valid = (
        (map_i >= 0)
        & (map_i <= texture.shape[0] - 1)
        & (map_j >= 0)
        & (map_j <= texture.shape[1] - 1)
    )
    return out, valid


def _subpixel(scores: F32, peak: tuple[int, int]) -> tuple[float, float]:
    r, c = peak
    out = [float(r), float(c)]
    for axis, (i, lim) in enumerate(((r, scores.shape[0]), (c, scores.shape[1]))):
        if 0 < i < lim - 1:
            if axis == 0:
                a, b, d = scores[r - 1, c], scores[r, c], scores[r + 1, c]
            else:
                a, b, d = scores[r, c - 1], scores[r, c], scores[r, c + 1]
            den = a - 2 * b + d
            if den < 0:
                out[axis] += float(np.clip(0.5 * (a - d) / den, -0.5, 0.5))
    return out[0], out[1]


def match_shift(
    mosaic: F32, mask: NDArray[np.bool_], reference: F32, max_shift_px: int
) -> tuple[float, float, float]:
    """(dr, dc, score) of the best translation of `mosaic` (h, w) with `mask` within a
    reference (h + 2S, w + 2S) that has S = `max_shift_px` more on each side."""
    m = np.ascontiguousarray(mosaic, np.float32)
    ref = np.ascontiguousarray(reference, np.float32)
    scores = cv2.matchTemplate(ref, m, cv2.TM_CCOEFF_NORMED, mask=mask.astype(np.float32))
    scores = np.nan_to_num(scores, nan=-1.0, posinf=-1.0, neginf=-1.0)
    peak = np.unravel_index(int(np.argmax(scores)), scores.shape)
    r, c = _subpixel(scores, (int(peak[0]), int(peak[1])))
    return r - max_shift_px, c - max_shift_px, float(scores[peak])


@dataclass(frozen=True)
class Alignment:
    """Global shift (px) and score; per tile: how many tiles had texture to match, the
    fraction of them whose best match scores >= 0.5 inside the search window (not on its
    edge: "matched"), and the median and 90th percentile of the matched tiles' shift
    magnitudes (px): the local misalignment. `shift_found`: the global best match scores
    >= 0.5 inside the +-`search_px` window; otherwise the mosaic is too far off (or too
    smeared) for its shift to mean anything."""

    shift_px: tuple[float, float]
    score: float
    search_px: int
    tiles: int
    tile_shift_median_px: float
    tile_shift_p90_px: float
    tiles_matched: float

    @property
    def shift_found(self) -> bool:
        return self.score >= 0.5 and max(map(abs, self.shift_px)) < self.search_px - 0.5

    def as_dict(self, gsd_m: float) -> dict[str, float | int | bool | list[float]]:
        return {
            "shift_found": self.shift_found,
            "shift_px": [round(self.shift_px[0], 2), round(self.shift_px[1], 2)],
            "shift_m": round(float(np.hypot(*self.shift_px)) * gsd_m, 3),
            "ncc": round(self.score, 4),
            "tiles": self.tiles,
            "tile_shift_median_px": round(self.tile_shift_median_px, 2),
            "tile_shift_p90_px": round(self.tile_shift_p90_px, 2),
            "tiles_matched": round(self.tiles_matched, 3),
        }


def _padded(ref: F32, ref_valid: NDArray[np.bool_], s: int) -> F32:
    out = np.where(ref_valid, ref, np.nan).astype(np.float32)
    out = np.pad(out, s, constant_values=np.nan)
    # matchTemplate needs finite values: fill the unknown with the mean (no structure)
    fill = float(np.nanmean(out)) if np.isfinite(out).any() else 0.0
    return np.where(np.isfinite(out), out, fill).astype(np.float32)


def align_to_reference(
    mosaic: NDArray,
    mask: NDArray[np.bool_],
    reference: F32,
    ref_valid: NDArray[np.bool_],
    *,
    max_shift_px: int = 40,
    tile_px: int = 128,
    tile_shift_px: int = 16,
) -> Alignment:
    """Compare a mosaic (grey or BGR) with a reference of the same grid (module docstring)."""
    grey = mosaic if mosaic.ndim == 2 else cv2.cvtColor(mosaic, cv2.COLOR_BGR2GRAY)
    grey = grey.astype(np.float32)
    use = mask & ref_valid
    s = max_shift_px
    padded = _padded(reference, ref_valid, s)
    dr, dc, score = match_shift(grey, use, padded, s)
    t, ts = tile_px, tile_shift_px
    tpad = _padded(reference, ref_valid, ts)
    shifts, scored = [], 0
    rows, cols = grey.shape
    for r in range(0, rows - t + 1, t):
        for c in range(0, cols - t + 1, t):
            m = use[r : r + t, c : c + t]
            if m.mean() < 0.8 or np.std(grey[r : r + t, c : c + t][m]) < 2.0:
                continue
            ref = tpad[r : r + t + 2 * ts, c : c + t + 2 * ts]
            tr, tc, sc = match_shift(grey[r : r + t, c : c + t], m, ref, ts)
            scored += 1
            if sc >= 0.5 and max(abs(tr), abs(tc)) < ts - 0.5:
                shifts.append(np.hypot(tr, tc))
    sh = np.asarray(shifts)
    return Alignment(
        shift_px=(dr, dc),
        score=score,
        search_px=max_shift_px,
        tiles=scored,
        tile_shift_median_px=float(np.median(sh)) if sh.size else float("nan"),
        tile_shift_p90_px=float(np.percentile(sh, 90)) if sh.size else float("nan"),
        tiles_matched=len(sh) / scored if scored else float("nan"),
    )
