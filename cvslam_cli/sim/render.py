"""What every simulated camera view returns, and the photometric model applied to it.

World-specific ray casting lives with each world (`terrain.py`: height field seen from above;
`yard.py`: ground and vertical walls seen from a ground robot). Both produce the ideal
radiance of each pixel of the raw (distorted) image plus the exact geometry behind it, and
`photometric` turns radiance into what a camera records (exposure gain and offset per frame,
sensor noise, 8-bit quantisation).
"""

from __future__ import annotations

from dataclasses import dataclass

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
    clipped and rounded."""
    img = (255.0 * gain) * radiance + 255.0 * offset
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, radiance.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
