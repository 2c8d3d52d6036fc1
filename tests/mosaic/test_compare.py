"""Alignment of a mosaic with a reference raster: known shifts come back, sub-pixel."""

from __future__ import annotations

import cv2
import numpy as np

from cvslam_cli.mosaic.compare import align_to_reference, resample_reference
from cvslam_cli.mosaic.project import CanvasGrid


def _texture(rng, shape):
    img = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)


def test_known_shift_and_gain_are_recovered():
    rng = np.random.default_rng(5)
    ref = _texture(rng, (420, 520))
    dr, dc = 3.4, -5.7  # mosaic[r, c] = ref[r + dr, c + dc]
    M = np.float32([[1, 0, dc], [0, 1, dr]])
    mosaic = cv2.warpAffine(ref, M, (520, 420), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    mosaic = 0.7 * mosaic + 20  # exposure differs: NCC does not care
    mask = np.zeros(mosaic.shape, bool)
    mask[30:390, 40:480] = True
    a = align_to_reference(mosaic, mask, ref, np.ones_like(mask), max_shift_px=10, tile_px=96)
    assert abs(a.shift_px[0] - dr) < 0.2 and abs(a.shift_px[1] - dc) < 0.2
    assert a.score > 0.95
    assert a.tiles_matched > 0.9
    assert abs(a.tile_shift_median_px - np.hypot(dr, dc)) < 0.5


def test_unrelated_images_do_not_match():
    rng = np.random.default_rng(6)
    ref, other = _texture(rng, (300, 300)), _texture(rng, (300, 300))
    mask = np.ones(ref.shape, bool)
    a = align_to_reference(other, mask, ref, mask, max_shift_px=8, tile_px=96)
    assert a.score < 0.3
    assert a.tiles_matched < 0.5


def test_reference_resampled_on_a_canvas_grid():
    """Texel (i, j) (row north, col east) at 4 px/m resampled at 0.5 m/px: canvas pixel
    centres land on the right texels."""
    tex = np.zeros((400, 400), np.uint8)
    tex[200:240, 100:120] = 255  # n in [50, 60), e in [25, 30) from the origin
    grid = CanvasGrid.covering(np.array([0.0, 0.0, 100.0, 100.0]), 0.5)
    out, ok = resample_reference(tex, (0.0, 0.0), 4.0, grid)
    assert ok.all()
    r, c = grid.pixel_of(np.array([55.0]), np.array([27.5]))
    assert out[round(r[0]), round(c[0])] > 200
    r, c = grid.pixel_of(np.array([45.0]), np.array([27.5]))
    assert out[round(r[0]), round(c[0])] < 50
