"""Adaptive SIFT (paper, section "Adaptive SIFT"): OpenCV's SIFT detector whose scale step
k = 2^(1/s) (s layers per octave) and contrast threshold are chosen per image from the energy
of its difference-of-Gaussian (DoG) response, so that low-texture images (sea, desert) still
give enough keypoints and high-texture images (buildings) do not flood the filter with
unstable ones.

The rule
--------
OpenCV rejects an extremum of the DoG D = G(k sigma) * I - G(sigma) * I (intensities in
[0, 1]) when |D| < contrastThreshold / s. Let r = `dog_rms(image)` be the RMS of D at the
reference spacing k0 = 2^(1/3) (scale sigma = 1.6 on the 2x-downsampled image, i.e. the first
scale of SIFT's octave 1).

1. *Why the DoG RMS normalises contrast.* D is linear in I: multiplying the image's contrast
   by a (haze, exposure, a bland surface) multiplies every DoG value, extrema included, by a.
   A fixed threshold therefore keeps almost everything on a contrasty image and almost
   nothing on a dull one. A threshold proportional to r keeps the extrema that stand out of
   the image's *own* DoG distribution by a fixed number of standard deviations: the count no
   longer depends on global contrast, only on the image's structure.
2. *The DoG amplitude scales with (k - 1).* For small steps, G(k sigma) - G(sigma) ~
   (k - 1) sigma dG/dsigma = (k - 1) sigma^2 laplacian(G), so at spacing k_s = 2^(1/s) the DoG
   RMS is r_s = r (k_s - 1) / (k0 - 1). The effective threshold is set to

       contrastThreshold / s = contrast_per_rms * r_s
       =>  contrastThreshold = s * contrast_per_rms * r * (k_s - 1) / (k0 - 1),

   clipped to [contrast_min, contrast_max].
3. *Why fewer layers for busy images.* Each octave is sampled at s + 3 scales, and the
   number of scale-space extrema grows with s (Lowe 2004, fig. 3): more layers find more,
   weaker and less repeatable extrema, fewer layers only the well-separated, stable ones.
   A busy image (large r) has extrema to spare, so it gets fewer layers; a smooth one (small r)
   needs finer scale sampling to find enough, so it gets more. With the starting point s0 =
   `sift.n_octave_layers` applying to an image of DoG RMS `dog_rms_ref`, one layer is added
   per halving of the DoG energy:

       s = clip(round(s0 + log2(dog_rms_ref / r)), layers_min, layers_max).

4. *Count bounds.* If fewer than `features_min` keypoints result, the detection is run once
   more with the threshold times `retry_factor` (not below `contrast_min`); if more than
   `features_max`, the strongest (largest |D|, OpenCV's `response`) are kept spread over the
   image: a grid of ~48 cells, best of every cell first, then second best, ... (uniform
   coverage constrains the pose better than clusters of strong corners).

What the rule gives on smooth, busy and real images: BENCHMARKS.md, "Feature extraction
(issue 4)", "Adaptive SIFT per texture".

Speed
-----
OpenCV always starts the pyramid from the image upsampled 2x (octave -1), which costs ~3/4 of
the time and adds only keypoints of scale below 1.6 full-resolution pixels, the least
repeatable ones. With `half_resolution_base` the image is downsampled 2x (INTER_AREA, pixel
u' covering full-resolution pixels 2u' and 2u' + 1) and OpenCV's upsampling (in its precise
mode, which maps index x to 2x) brings it back to full resolution: the pyramid then starts at
the original image. Keypoints map back as u = 2 u' + 0.5, size x 2, octave + 1 (tested on
blobs at known positions, to < 0.1 px); it is several times faster than the upsampled base.

Detection and description run in one OpenCV pass (`detectAndCompute`), and the cap then drops
rows: describing only the kept keypoints (`compute`) rebuilds the whole Gaussian pyramid,
which costs more than the descriptors it saves unless the cap drops hundreds of keypoints
(BENCHMARKS.md, "Feature extraction (issue 4)", "Adaptive SIFT per texture").
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cvslam_cli.config import AdaptiveSiftConfig, SiftConfig
from cvslam_cli.records.arrays import F32, I32, I64, U8
from cvslam_cli.records.features import DESCRIPTOR_SIZE

REFERENCE_LAYERS = 3
"""The DoG RMS of `dog_rms` is measured at the spacing k0 = 2^(1/REFERENCE_LAYERS)."""
GRID_CELLS = 48
"""Cells of the grid that spreads the kept keypoints over the image (about 8 x 6 at 4:3)."""
_RMS_FLOOR = 1e-7  # below this the image has no structure (constant up to rounding)


@dataclass(frozen=True, eq=False)
class Keypoints:
    """SIFT keypoints of one image (N of them).

    uv_raw_px: (N, 2) float32 pixel coordinates in the image as given (OpenCV convention:
        integers at pixel centres). size_px, angle_deg, response: (N,) float32 as OpenCV
        reports them (size in full-resolution pixels; response = |DoG| at the extremum).
    octave: (N,) int32 octave index relative to the original resolution (-1 = the 2x
        upsampled level, 0 = full resolution, 1 = half, ...).
    desc: (N, 128) uint8 SIFT descriptors (OpenCV's float descriptors are integer-valued).
    """

    uv_raw_px: F32
    size_px: F32
    angle_deg: F32
    response: F32
    octave: I32
    desc: U8

    def __len__(self) -> int:
        return int(self.uv_raw_px.shape[0])

    @staticmethod
    def empty() -> Keypoints:
        z = np.zeros(0, np.float32)
        return Keypoints(
            uv_raw_px=np.zeros((0, 2), np.float32),
            size_px=z,
            angle_deg=z.copy(),
            response=z.copy(),
            octave=np.zeros(0, np.int32),
            desc=np.zeros((0, DESCRIPTOR_SIZE), np.uint8),
        )


@dataclass(frozen=True)
class SiftStats:
    """What the detector did with one image (a row of the per-frame CSV).

    dog_rms: RMS of the DoG at the reference spacing ([0, 1] intensities).
    n_octave_layers, contrast_threshold: the OpenCV parameters finally used.
    n_detected: keypoints found (after the retry, if any); n_kept: after the cap.
    retried: the detection was repeated with a lower threshold.
    detect_s: wall time of the DoG RMS and the OpenCV pass(es), which detect *and* describe
    (one pyramid, module docstring); describe_s: wall time of the selection and the conversion
    of the kept keypoints and descriptors to arrays.
    """

    dog_rms: float
    n_octave_layers: int
    contrast_threshold: float
    n_detected: int
    n_kept: int
    retried: bool
    detect_s: float
    describe_s: float


# --------------------------------------------------------------------------- image prep


def to_grey_u8(image: np.ndarray) -> U8:
    """A 2-D uint8 image from grey or colour (BGR/BGRA) uint8, uint16 or float input.

    uint16: the bit depth is taken from the largest value (10-, 12- or 16-bit data in a 16-bit
    container) and the top 8 bits kept. float: [0, 1] if its maximum is <= 1, else [0, 255].
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.size:
        if img.shape[2] not in (3, 4):
            raise ValueError(f"image has {img.shape[2]} channels, expected 1, 3 or 4")
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        if img.dtype not in (np.uint8, np.uint16, np.float32):
            img = img.astype(np.float32)
        img = cv2.cvtColor(img, code)
    if img.ndim != 2:
        if img.size == 0:
            return np.zeros((0, 0), np.uint8)
        raise ValueError(f"image has shape {img.shape}, expected (H, W) or (H, W, C)")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.size == 0:
        return np.zeros(img.shape, np.uint8)
    if np.issubdtype(img.dtype, np.integer):
        top = int(img.max())
        shift = max(0, top.bit_length() - 8)
        return (np.clip(img, 0, None) >> shift).astype(np.uint8)
    f = img.astype(np.float32)
    f = np.nan_to_num(f, nan=0.0, posinf=0.0, neginf=0.0)
    scale = 255.0 if float(f.max()) <= 1.0 else 1.0
    return np.clip(np.rint(f * scale), 0, 255).astype(np.uint8)


def half_resolution(grey: U8) -> U8:
    """2x downsampling (INTER_AREA) of the even-sized top-left part: pixel (u', v') is the
    mean of full-resolution pixels 2u'..2u'+1, 2v'..2v'+1, centred at (2u' + 0.5, 2v' + 0.5)."""
    h, w = grey.shape[0] // 2, grey.shape[1] // 2
    if h == 0 or w == 0:
        return np.zeros((h, w), np.uint8)
    even = grey[: 2 * h, : 2 * w]
    return cv2.resize(even, (w, h), interpolation=cv2.INTER_AREA)


def _dog_rms_of_half(half: U8, sigma: float) -> float:
    if half.size == 0:
        return 0.0
    f = half.astype(np.float32) * np.float32(1.0 / 255.0)
    g1 = cv2.GaussianBlur(f, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
    # G(k sigma) = G(sigma) convolved with G(sigma sqrt(k^2 - 1)): cheaper than from scratch
    k = 2.0 ** (1.0 / REFERENCE_LAYERS)
    g2 = cv2.GaussianBlur(g1, (0, 0), sigma * math.sqrt(k * k - 1.0))
    return float(cv2.norm(g2, g1, cv2.NORM_L2)) / math.sqrt(f.size)


def dog_rms(image: np.ndarray, sigma: float = 1.6) -> float:
    """RMS of the difference-of-Gaussian G(k sigma) - G(sigma) (k = 2^(1/3)) of the image
    scaled to [0, 1], computed on its 2x-downsampled version (a quarter of the pixels: cheap
    next to detection); 0 for an empty or constant image."""
    grey = to_grey_u8(image)
    return _dog_rms_of_half(half_resolution(grey), sigma)


# --------------------------------------------------------------------------- the rule


def adaptive_parameters(
    rms: float, sift: SiftConfig, adaptive: AdaptiveSiftConfig
) -> tuple[int, float]:
    """(layers per octave s, OpenCV contrastThreshold) for an image of DoG RMS `rms`
    (derivation in the module docstring)."""
    lo, hi = adaptive.layers_min, max(adaptive.layers_min, adaptive.layers_max)
    if rms <= _RMS_FLOOR:
        return hi, adaptive.contrast_min
    s = round(sift.n_octave_layers + math.log2(adaptive.dog_rms_ref / rms))
    s = int(min(hi, max(lo, s)))
    k_s, k0 = 2.0 ** (1.0 / s), 2.0 ** (1.0 / REFERENCE_LAYERS)
    dog_threshold = adaptive.contrast_per_rms * rms * (k_s - 1.0) / (k0 - 1.0)
    c_hi = max(adaptive.contrast_min, adaptive.contrast_max)
    return s, float(min(c_hi, max(adaptive.contrast_min, s * dog_threshold)))


def select_spread(
    uv_px: F32, response: F32, width: int, height: int, n_keep: int, cells: int = GRID_CELLS
) -> I64:
    """Indices of `n_keep` keypoints spread over a grid of ~`cells` square-ish cells: every
    cell's strongest first, then every cell's second strongest, ... (ties by response).
    Returned in ascending index order."""
    n = int(uv_px.shape[0])
    if n <= n_keep:
        return np.arange(n, dtype=np.int64)
    if n_keep <= 0:
        return np.zeros(0, np.int64)
    side = math.sqrt(max(width * height, 1) / cells)
    nx, ny = max(1, round(width / side)), max(1, round(height / side))
    cx = np.clip((uv_px[:, 0] * (nx / max(width, 1))).astype(np.int64), 0, nx - 1)
    cy = np.clip((uv_px[:, 1] * (ny / max(height, 1))).astype(np.int64), 0, ny - 1)
    cell = cy * nx + cx
    order = np.lexsort((-response.astype(np.float64), cell))  # by cell, strongest first
    sorted_cell = cell[order]
    starts = np.flatnonzero(np.r_[True, sorted_cell[1:] != sorted_cell[:-1]])
    counts = np.diff(np.r_[starts, n])
    rank = np.arange(n) - np.repeat(starts, counts)  # rank inside its cell
    pick = np.lexsort((-response[order].astype(np.float64), rank))[:n_keep]
    return np.sort(order[pick])


# --------------------------------------------------------------------------- detection


def _make_sift(n_layers: int, contrast: float, sift: SiftConfig) -> cv2.SIFT:
    # precise upscaling maps index x to 2x (no 0.25 px bias; the half-resolution mapping
    # below relies on it)
    return cv2.SIFT_create(
        0, int(n_layers), float(contrast), float(sift.edge_threshold), float(sift.sigma),
        cv2.CV_8U, True,
    )  # fmt: skip


def _keypoint_arrays(
    kps: Sequence[cv2.KeyPoint],
) -> tuple[F32, F32, F32, F32, I32]:
    n = len(kps)
    if n == 0:
        z = np.zeros(0, np.float32)
        return np.zeros((0, 2), np.float32), z, z.copy(), z.copy(), np.zeros(0, np.int32)
    uv = cv2.KeyPoint_convert(kps).astype(np.float32).reshape(n, 2)
    size = np.fromiter((k.size for k in kps), np.float32, n)
    angle = np.fromiter((k.angle for k in kps), np.float32, n)
    response = np.fromiter((k.response for k in kps), np.float32, n)
    packed = np.fromiter((k.octave for k in kps), np.int64, n)
    octave = ((packed & 255) ^ 128) - 128  # low byte, signed (OpenCV's unpackOctave)
    return uv, size, angle, response, octave.astype(np.int32)


def detect_and_describe(
    image: np.ndarray, sift: SiftConfig, adaptive: AdaptiveSiftConfig
) -> tuple[Keypoints, SiftStats]:
    """Adaptive (or, with `adaptive.enabled` false, fixed) SIFT keypoints and descriptors of
    one image (grey uint8 (H, W); uint16 and colour are converted). Coordinates, sizes and
    octaves refer to the image as given, whichever `half_resolution_base`."""
    t0 = time.perf_counter()
    grey = to_grey_u8(image)
    half = half_resolution(grey)
    rms = _dog_rms_of_half(half, sift.sigma) if half.size else 0.0
    use_half = sift.half_resolution_base and min(half.shape) >= 8
    fed = half if use_half else grey

    if adaptive.enabled:
        n_layers, contrast = adaptive_parameters(rms, sift, adaptive)
    else:
        n_layers, contrast = sift.n_octave_layers, sift.contrast_threshold

    if grey.size == 0 or (adaptive.enabled and rms <= _RMS_FLOOR):
        # no structure: no DoG extremum passes any positive threshold
        stats = SiftStats(rms, n_layers, contrast, 0, 0, False, time.perf_counter() - t0, 0.0)
        return Keypoints.empty(), stats

    detector = _make_sift(n_layers, contrast, sift)
    kps, desc = detector.detectAndCompute(fed, None)
    retried = False
    if adaptive.enabled and len(kps) < adaptive.features_min:
        lower = max(contrast * adaptive.retry_factor, adaptive.contrast_min)
        if lower < contrast:
            retried, contrast = True, lower
            detector = _make_sift(n_layers, contrast, sift)
            kps, desc = detector.detectAndCompute(fed, None)
    t1 = time.perf_counter()

    n_detected = len(kps)
    uv, size, angle, response, octave = _keypoint_arrays(kps)
    desc = (
        np.zeros((0, DESCRIPTOR_SIZE), np.uint8)
        if desc is None or n_detected == 0
        else np.asarray(desc, dtype=np.uint8).reshape(n_detected, DESCRIPTOR_SIZE)
    )
    if adaptive.enabled and n_detected > adaptive.features_max:
        keep = select_spread(uv, response, fed.shape[1], fed.shape[0], adaptive.features_max)
        uv, size, angle, response, octave = (a[keep] for a in (uv, size, angle, response, octave))
        desc = desc[keep]
    if use_half:  # back to the original resolution (module docstring)
        uv = uv * np.float32(2.0) + np.float32(0.5)
        size = size * np.float32(2.0)
        octave = octave + np.int32(1)
    keypoints = Keypoints(uv, size, angle, response, octave, np.ascontiguousarray(desc))
    t2 = time.perf_counter()
    stats = SiftStats(
        dog_rms=rms,
        n_octave_layers=int(n_layers),
        contrast_threshold=float(contrast),
        n_detected=n_detected,
        n_kept=len(keypoints),
        retried=retried,
        detect_s=t1 - t0,
        describe_s=t2 - t1,
    )
    return keypoints, stats
