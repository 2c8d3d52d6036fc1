"""Blending warped images into one canvas, incrementally, in float32.

Two methods, the same ones as OpenCV's stitching blenders (`cv2.detail_FeatherBlender`,
`cv2.detail_MultiBandBlender`), accumulated in float32 here: OpenCV's accumulate weighted
sums in int16, which overflow (bright pixels turn black) once more than ~128 images overlap,
and a downward camera at 10 Hz sees each ground point in dozens to hundreds of frames.

- feather: each image weighted by its distance from the edge of its valid mask times
  `sharpness`, capped at 1 (OpenCV's weight map); overlaps fade from one image into the
  next instead of cutting, and image centres count more than edges.
- multiband (Burt & Adelson 1983): each image's Laplacian pyramid (`bands` levels) weighted
  by the Gaussian pyramid of its mask; low frequencies (exposure) are blended over wide
  zones, detail over narrow ones, so seams vanish without blurring detail.

`Compositor.feed` adds one image at its canvas position (`prepare` + `add`: an image
prepared once can be added to several canvases, e.g. a vehicle's and the merged one, at
offsets that are multiples of `unit`); the accumulators are the size of the canvas
(feather: channels + 1 floats per pixel; multiband: 4/3 of that for the pyramid), so
memory depends on the canvas, never on how many images are fed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

BlendKind = Literal["feather", "multiband"]


@dataclass(frozen=True, eq=False)
class Blended:
    """`image` (H, W) grey or (H, W, 3) BGR uint8 (0 where nothing fell); `mask` (H, W)
    bool, True where some image contributed; `offset_rc` the canvas (row, col) of the
    top-left pixel (after cropping to content)."""

    image: NDArray[np.uint8]
    mask: NDArray[np.bool_]
    offset_rc: tuple[int, int]

    @property
    def covered_px(self) -> int:
        return int(self.mask.sum())


def feather_weights(mask: NDArray[np.uint8], sharpness: float) -> NDArray[np.float32]:
    """OpenCV's feather weight map: L1 distance to the mask's edge x sharpness, capped at 1.
    The patch's border counts as an edge (distanceTransform alone would treat it as far
    away: a mask valid up to the border would get full weight there, a hard cut)."""
    padded = cv2.copyMakeBorder(mask, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    w = cv2.distanceTransform(padded, cv2.DIST_L1, 3)[1:-1, 1:-1]
    return np.minimum(w * np.float32(sharpness), np.float32(1.0))


@dataclass(frozen=True, eq=False)
class Contribution:
    """One image ready to accumulate: per level k (one for feather, bands + 1 for multiband)
    the weighted image (h_k, w_k, channels) float32 and the weights (h_k, w_k); level 0's
    top-left pixel at (row0, col0) of the canvas it was prepared on."""

    levels: tuple[tuple[NDArray[np.float32], NDArray[np.float32]], ...]
    row0: int
    col0: int
    channels: int


class Compositor:
    """Blends images fed at canvas positions into a canvas of `shape` (rows, cols)."""

    def __init__(
        self,
        shape: tuple[int, int],
        kind: BlendKind = "feather",
        *,
        sharpness: float = 0.02,
        bands: int = 5,
    ) -> None:
        if kind not in ("feather", "multiband"):
            raise ValueError(f"unknown blend {kind!r} (feather or multiband)")
        self.shape = (int(shape[0]), int(shape[1]))
        self.kind = kind
        self.sharpness = float(sharpness)
        self.bands = int(bands) if kind == "multiband" else 0
        self.fed = 0
        self.channels = 0  # set by the first image fed
        self._acc: list[NDArray[np.float32]] = []
        self._wsum: list[NDArray[np.float32]] = []

    # -- accumulators ---------------------------------------------------------------------

    def _allocate(self, channels: int) -> None:
        self.channels = channels
        unit = 1 << self.bands
        h = -(-self.shape[0] // unit) * unit
        w = -(-self.shape[1] // unit) * unit
        for _ in range(self.bands + 1):
            self._acc.append(np.zeros((h, w, channels), np.float32))
            self._wsum.append(np.zeros((h, w), np.float32))
            h, w = h // 2, w // 2

    def _conform(self, image: NDArray) -> NDArray[np.float32]:
        img = image
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        channels = 1 if img.ndim == 2 else 3
        if not self.channels:
            self._allocate(channels)
        if channels != self.channels:
            code = cv2.COLOR_GRAY2BGR if channels == 1 else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(img, code)
        img = img.astype(np.float32)
        return img[:, :, None] if img.ndim == 2 else img

    @property
    def unit(self) -> int:
        """Canvas positions a prepared contribution can be moved by: multiples of this (the
        coarsest pyramid level's pixel for multiband, 1 for feather)."""
        return 1 << self.bands

    def feed(self, image: NDArray, mask: NDArray[np.uint8], row0: int, col0: int) -> None:
        """Add `image` (h, w[, 3]) uint8 with `mask` (h, w) uint8 (255 valid) whose top-left
        pixel goes to canvas (row0, col0); the patch must lie inside the canvas."""
        contribution = self.prepare(image, mask, row0, col0)
        if contribution is not None:
            self.add(contribution)

    def prepare(
        self, image: NDArray, mask: NDArray[np.uint8], row0: int, col0: int
    ) -> Contribution | None:
        """The weighted image (feather) or weighted pyramid (multiband) of a patch placed at
        (row0, col0) of this canvas, to `add` here and to other canvases (the same work
        done once); None when the mask is empty."""
        h, w = mask.shape
        if row0 < 0 or col0 < 0 or row0 + h > self.shape[0] or col0 + w > self.shape[1]:
            raise ValueError(
                f"patch {w}x{h} at ({row0}, {col0}) outside the canvas "
                f"{self.shape[1]}x{self.shape[0]}"
            )
        if not mask.any():
            return None
        img = self._conform(image)
        if self.kind == "feather":
            wgt = feather_weights(mask, self.sharpness)
            return Contribution(((img * wgt[:, :, None], wgt),), row0, col0, self.channels)
        return self._prepare_multiband(img, mask, row0, col0)

    def add(self, c: Contribution, row_offset: int = 0, col_offset: int = 0) -> None:
        """Accumulate a contribution prepared on a canvas whose origin is at (row_offset,
        col_offset) of this one (multiples of `unit`); what falls outside is dropped."""
        if len(c.levels) != self.bands + 1:
            raise ValueError(f"a contribution of {len(c.levels)} levels to a {self.kind} canvas")
        if row_offset % self.unit or col_offset % self.unit:
            raise ValueError(f"offset ({row_offset}, {col_offset}) not a multiple of {self.unit}")
        if not self.channels:
            self._allocate(c.channels)
        if c.channels != self.channels:
            raise ValueError(
                f"{c.channels}-channel contribution to a {self.channels}-channel canvas"
            )
        for k, (acc_part, w_part) in enumerate(c.levels):
            s = 1 << k
            r0, c0 = (c.row0 - row_offset) // s, (c.col0 - col_offset) // s
            H, W = self._wsum[k].shape
            h, w = w_part.shape
            a0, b0 = max(0, -r0), max(0, -c0)
            a1, b1 = min(h, H - r0), min(w, W - c0)
            if a1 <= a0 or b1 <= b0:
                return
            dst = (slice(r0 + a0, r0 + a1), slice(c0 + b0, c0 + b1))
            self._acc[k][dst] += acc_part[a0:a1, b0:b1]
            self._wsum[k][dst] += w_part[a0:a1, b0:b1]
        self.fed += 1

    def _prepare_multiband(
        self, img: NDArray[np.float32], mask: NDArray[np.uint8], row0: int, col0: int
    ) -> Contribution:
        unit = self.unit
        H, W = -(-self.shape[0] // unit) * unit, -(-self.shape[1] // unit) * unit
        # the patch grown by a margin and aligned to the coarsest level's pixels
        r0 = max(0, (row0 - unit) // unit * unit)
        c0 = max(0, (col0 - unit) // unit * unit)
        r1 = min(H, -(-(row0 + mask.shape[0] + unit) // unit) * unit)
        c1 = min(W, -(-(col0 + mask.shape[1] + unit) // unit) * unit)
        valid = mask > 0
        big = np.zeros((r1 - r0, c1 - c0, self.channels), np.float32)
        m = np.zeros((r1 - r0, c1 - c0), np.float32)
        pr, pc = row0 - r0, col0 - c0
        sl = (slice(pr, pr + mask.shape[0]), slice(pc, pc + mask.shape[1]))
        big[sl] = np.where(valid[:, :, None], img, 0.0)
        m[sl] = valid
        # outside the mask: a smooth continuation of the content (no artificial edge at the
        # mask border for the Laplacian levels to carry across it)
        gauss = _extrapolate(big, m)
        levels = []
        for k in range(self.bands + 1):
            down = _down(gauss) if k < self.bands else None
            lap = gauss - _up(down, gauss.shape) if down is not None else gauss
            levels.append((lap * m[:, :, None], m))
            if down is not None:
                gauss = down
                m = cv2.pyrDown(m)
        return Contribution(tuple(levels), r0, c0, self.channels)

    # -- result -------------------------------------------------------------------------

    def result(self, crop: bool = True) -> Blended:
        """The blended canvas, cropped to the pixels some image covered (`crop`)."""
        rows, cols = self.shape
        if not self.channels:
            return Blended(np.zeros((0, 0), np.uint8), np.zeros((0, 0), bool), (0, 0))
        if self.kind == "feather":
            w = self._wsum[0]
            out = self._acc[0] / np.maximum(w, 1e-12)[:, :, None]
        else:
            out = self._acc[-1] / np.maximum(self._wsum[-1], 1e-6)[:, :, None]
            for k in range(self.bands - 1, -1, -1):
                out = (
                    _up(out, self._acc[k].shape)
                    + self._acc[k] / np.maximum(self._wsum[k], 1e-6)[:, :, None]
                )
        mask = self._wsum[0][:rows, :cols] > 0
        img = np.clip(np.rint(out[:rows, :cols]), 0, 255).astype(np.uint8)
        img = img[:, :, 0] if self.channels == 1 else img
        img[~mask] = 0
        r0, c0 = 0, 0
        if crop and mask.any():
            rr = np.flatnonzero(mask.any(axis=1))
            cc = np.flatnonzero(mask.any(axis=0))
            r0, r1, c0, c1 = int(rr[0]), int(rr[-1]) + 1, int(cc[0]), int(cc[-1]) + 1
            img, mask = img[r0:r1, c0:c1], mask[r0:r1, c0:c1]
        return Blended(np.ascontiguousarray(img), np.ascontiguousarray(mask), (r0, c0))


def _extrapolate(img: NDArray[np.float32], valid: NDArray[np.float32]) -> NDArray[np.float32]:
    """`img` (h, w, c) kept where `valid` (h, w) is 1 and continued smoothly elsewhere
    (push-pull: mask-normalised pyramid averages, each level filling the holes of the next
    finer one)."""
    imgs, ws = [img * valid[:, :, None]], [valid]
    while min(ws[-1].shape) > 2:
        imgs.append(_down(imgs[-1]))
        ws.append(cv2.pyrDown(ws[-1]))
    out = imgs[-1] / np.maximum(ws[-1], 1e-6)[:, :, None]
    if (ws[-1] <= 1e-6).any():
        out[ws[-1] <= 1e-6] = img[valid > 0].mean(axis=0)
    for k in range(len(imgs) - 2, -1, -1):
        known = valid if k == 0 else np.minimum(ws[k] * 4.0, 1.0)
        cur = imgs[k] / np.maximum(ws[k], 1e-6)[:, :, None]
        out = known[:, :, None] * cur + (1.0 - known[:, :, None]) * _up(out, imgs[k].shape)
    return out


def _down(img: NDArray[np.float32]) -> NDArray[np.float32]:
    """pyrDown of an (h, w, c) image, keeping the channel axis when c == 1."""
    out = cv2.pyrDown(img)
    return out[:, :, None] if out.ndim == 2 else out


def _up(img: NDArray[np.float32], shape: tuple[int, ...]) -> NDArray[np.float32]:
    """pyrUp of an (h, w, c) image to `shape` (rows, cols, c), keeping the channel axis."""
    out = cv2.pyrUp(img, dstsize=(shape[1], shape[0]))
    return out[:, :, None] if out.ndim == 2 else out
