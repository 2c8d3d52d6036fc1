"""Procedural textures for simulated worlds (orthophotos, walls).

Two kinds of surface, so that the adaptive SIFT of `cvslam extract` has something to adapt to:
- *smooth* ("sea", "desert"): large gentle variations and a faint grain, few strong corners;
- *busy* ("urban"): buildings (rectangles of varied brightness with shadows), a road grid
  and fine clutter: many corners and blobs at every scale.
All functions return float32 images in [0, 1] and are deterministic given the generator.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.records.arrays import F32


def fractal_noise(
    shape: tuple[int, int],
    rng: np.random.Generator,
    *,
    base_px: float,
    octaves: int = 5,
    persistence: float = 0.5,
) -> F32:
    """Sum of `octaves` bicubically upsampled random grids; the coarsest has cells of
    `base_px` pixels, each next octave half that size with `persistence` times the amplitude.
    Normalised to [0, 1]."""
    h, w = shape
    out = np.zeros(shape, np.float32)
    amp, cell = 1.0, float(base_px)
    for _ in range(octaves):
        gh, gw = max(2, int(np.ceil(h / cell)) + 2), max(2, int(np.ceil(w / cell)) + 2)
        grid = rng.random((gh, gw), dtype=np.float32)
        up = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
        out += amp * up[:h, :w]
        amp *= persistence
        cell = max(cell / 2.0, 1.0)
    lo, hi = float(out.min()), float(out.max())
    return (out - lo) / max(hi - lo, 1e-6)


def smooth_texture(shape: tuple[int, int], rng: np.random.Generator, *, px_per_m: float) -> F32:
    """Sea/desert-like: dunes tens of metres across, a faint grain, and sparse rocks or
    shrubs (about one per 60 m^2, 0.3-2 m across, low contrast): few, weak features."""
    h, w = shape
    dunes = fractal_noise(shape, rng, base_px=40.0 * px_per_m, octaves=5, persistence=0.55)
    grain = fractal_noise(shape, rng, base_px=max(1.0, 0.6 * px_per_m), octaves=2)
    img = (0.45 + 0.35 * (dunes - 0.5) + 0.06 * (grain - 0.5)).astype(np.float32)
    n_rocks = int(h * w / (60.0 * px_per_m * px_per_m))
    xs, ys = rng.uniform(0, w, n_rocks), rng.uniform(0, h, n_rocks)
    radii = rng.uniform(0.15, 1.0, n_rocks) * px_per_m
    shades = rng.uniform(-0.18, 0.10, n_rocks)
    for x, y, r, d in zip(xs, ys, radii, shades, strict=True):
        shade = float(np.clip(img[int(y), int(x)] + d, 0, 1))
        cv2.circle(img, (int(x), int(y)), max(1, round(r)), shade, -1)
    return np.clip(cv2.GaussianBlur(img, (0, 0), 0.4 * px_per_m), 0, 1).astype(np.float32)


def busy_texture(shape: tuple[int, int], rng: np.random.Generator, *, px_per_m: float) -> F32:
    """Urban-like: a road grid, buildings with varied roofs and shadows, fine clutter."""
    h, w = shape
    img = 0.35 + 0.15 * fractal_noise(shape, rng, base_px=8.0 * px_per_m, octaves=3)
    block_px = max(8, int(30.0 * px_per_m))
    road_px = max(2, int(5.0 * px_per_m))
    img = img.astype(np.float32)
    for by in range(0, h, block_px):
        for bx in range(0, w, block_px):
            n_buildings = int(rng.integers(2, 6))
            for _ in range(n_buildings):
                bw = int(rng.uniform(0.15, 0.45) * (block_px - road_px))
                bh = int(rng.uniform(0.15, 0.45) * (block_px - road_px))
                x0 = bx + road_px + int(rng.uniform(0, block_px - road_px - bw))
                y0 = by + road_px + int(rng.uniform(0, block_px - road_px - bh))
                roof = float(rng.uniform(0.15, 0.95))
                shadow = max(1, int(0.15 * min(bw, bh)))
                cv2.rectangle(
                    img, (x0 + shadow, y0 + shadow), (x0 + bw + shadow, y0 + bh + shadow), 0.12, -1
                )
                cv2.rectangle(img, (x0, y0), (x0 + bw, y0 + bh), roof, -1)
            cv2.rectangle(img, (bx, by), (bx + block_px, by + road_px), 0.25, -1)
            cv2.rectangle(img, (bx, by), (bx + road_px, by + block_px), 0.25, -1)
    clutter = fractal_noise(shape, rng, base_px=max(1.0, 1.0 * px_per_m), octaves=2)
    return np.clip(img + 0.08 * (clutter - 0.5), 0, 1).astype(np.float32)


def to_uint8(img: F32) -> NDArray[np.uint8]:
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
