"""What every simulated camera view returns, and the photometric model applied to it.

World-specific ray casting lives with each world (`terrain.py`: height field seen from above;
`yard.py`: ground and vertical walls seen from a ground robot). Both produce the ideal
radiance of each pixel of the raw (distorted) image plus the exact geometry behind it, and
`photometric` turns radiance into what a camera records (exposure gain and offset per frame,
sensor noise, 8-bit quantisation).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One rendered view of size (H, W).

    radiance: (H, W) float32 in [0, 1], noise-free, before exposure.
    depth_m: (H, W) float32, z of the seen surface point in the camera optical frame
        (NaN where nothing is hit, e.g. sky).
    p_nav_m: (H, W, 3) float32 nav-frame (NED) position of the seen surface point, or None
        when not requested.
    valid: (H, W) bool, a surface point was hit.
    """

    radiance: NDArray[np.float32]
    depth_m: NDArray[np.float32]
    p_nav_m: NDArray[np.float32] | None
    valid: NDArray[np.bool_]


def photometric(
    radiance: NDArray[np.float32],
    *,
    gain: float,
    offset: float,
    noise_sigma: float,
    rng: np.random.Generator,
) -> NDArray[np.uint8]:
    """Recorded 8-bit image: 255 * (gain * radiance + offset) + N(0, noise_sigma) grey levels,
    rounded and clipped. The noise comes from OpenCV's generator (faster than numpy's for a
    full image: BENCHMARKS.md, "Figures from docstrings"), seeded from `rng` so the
    result is still determined by it."""
    img = radiance * np.float32(255.0 * gain) + np.float32(255.0 * offset)
    if noise_sigma > 0:
        noise = np.empty(radiance.shape, np.float32)
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        cv2.randn(noise, 0.0, float(noise_sigma))
        img += noise
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
