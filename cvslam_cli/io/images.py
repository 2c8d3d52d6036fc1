"""Image decoding/encoding for sensor_msgs/msg/Image and sensor_msgs/msg/CompressedImage.

Decoded images are numpy arrays: (H, W) for mono encodings (uint8 or uint16), (H, W, 3)
BGR for colour (alpha dropped; uint8, or uint16 for the 16-bit encodings), which is what
OpenCV expects downstream. Bayer mosaics (bayer_rggb8 ... bayer_grbg16) are demosaiced and
YUV 4:2:2 (yuv422 = UYVY, yuv422_yuy2 = YUYV) converted to BGR by OpenCV's conversions,
with the pattern names cv_bridge gives them.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

# encoding -> (dtype, channels)
RAW_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),
    "8UC3": (np.dtype(np.uint8), 3),
    "8UC4": (np.dtype(np.uint8), 4),
    "rgb16": (np.dtype(np.uint16), 3),
    "bgr16": (np.dtype(np.uint16), 3),
    "rgba16": (np.dtype(np.uint16), 4),
    "bgra16": (np.dtype(np.uint16), 4),
    "16UC3": (np.dtype(np.uint16), 3),
    "16UC4": (np.dtype(np.uint16), 4),
    "yuv422": (np.dtype(np.uint8), 2),
    "yuv422_yuy2": (np.dtype(np.uint8), 2),
    **{
        f"bayer_{p}{b}": (np.dtype(f"uint{b}"), 1)
        for p in ("rggb", "bggr", "gbrg", "grbg")
        for b in (8, 16)
    },
}
# Bayer pattern (as ROS names it, from the top-left pixel) -> OpenCV demosaicing code
_BAYER = {
    p: getattr(cv2, f"COLOR_Bayer{p.upper()}2BGR", getattr(cv2, f"COLOR_Bayer{legacy}2BGR"))
    for p, legacy in (("rggb", "BG"), ("bggr", "RG"), ("gbrg", "GR"), ("grbg", "GB"))
}
_TO_BGR = {
    "rgb8": cv2.COLOR_RGB2BGR,
    "rgb16": cv2.COLOR_RGB2BGR,
    "rgba8": cv2.COLOR_RGBA2BGR,
    "rgba16": cv2.COLOR_RGBA2BGR,
    "bgra8": cv2.COLOR_BGRA2BGR,
    "bgra16": cv2.COLOR_BGRA2BGR,
    "8UC4": cv2.COLOR_BGRA2BGR,
    "16UC4": cv2.COLOR_BGRA2BGR,
    "yuv422": cv2.COLOR_YUV2BGR_UYVY,
    "yuv422_yuy2": cv2.COLOR_YUV2BGR_YUY2,
    **{f"bayer_{p}{b}": code for p, code in _BAYER.items() for b in (8, 16)},
}


class ImageDecodeError(ValueError):
    """The message cannot be turned into an image; the caller adds file and topic."""


def decode_raw(msg: Any) -> tuple[np.ndarray, str]:
    """sensor_msgs/msg/Image -> (array, encoding)."""
    encoding = msg.encoding
    if encoding not in RAW_ENCODINGS:
        raise ImageDecodeError(
            f"unknown image encoding {encoding!r} (supported: {', '.join(RAW_ENCODINGS)})"
        )
    dtype, channels = RAW_ENCODINGS[encoding]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * dtype.itemsize
    if h <= 0 or w <= 0:
        raise ImageDecodeError(f"image has no pixels ({w}x{h})")
    if step < row_bytes or len(msg.data) < step * h:
        raise ImageDecodeError(
            f"image data holds {len(msg.data)} bytes, expected "
            f"{h} rows of {max(step, row_bytes)} bytes ({w}x{h} {encoding})"
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8, count=step * h).reshape(h, step)
    if step != row_bytes:
        buf = buf[:, :row_bytes]
    big = bool(msg.is_bigendian)
    arr = buf.view(dtype.newbyteorder(">" if big else "<")) if dtype.itemsize > 1 else buf
    arr = arr.reshape(h, w, channels) if channels > 1 else arr.reshape(h, w)
    if dtype.itemsize > 1 and big:
        arr = arr.astype(dtype)
    code = _TO_BGR.get(encoding)
    if code is not None:
        arr = cv2.cvtColor(np.ascontiguousarray(arr), code)
    return arr, encoding


def decode_compressed(msg: Any) -> tuple[np.ndarray, str]:
    """sensor_msgs/msg/CompressedImage (jpeg, png) -> (array, format)."""
    fmt = str(msg.format).lower()
    if not any(k in fmt for k in ("jpeg", "jpg", "png")):
        raise ImageDecodeError(
            f"unknown compressed image format {msg.format!r} (supported: jpeg, png)"
        )
    data = np.frombuffer(msg.data, dtype=np.uint8)
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if arr is None:
        raise ImageDecodeError(f"compressed image ({msg.format}) could not be decoded")
    if arr.ndim == 3 and arr.shape[2] == 4:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR)
    if "mono" in fmt and arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
    return arr, str(msg.format)


def raw_fields(image: np.ndarray) -> dict[str, Any]:
    """Fields of a sensor_msgs/msg/Image for a (H, W) mono or (H, W, 3) BGR array."""
    img = np.ascontiguousarray(image)
    if img.ndim == 2 and img.dtype == np.uint8:
        encoding = "mono8"
    elif img.ndim == 2 and img.dtype == np.uint16:
        encoding = "mono16"
        img = img.astype("<u2", copy=False)
    elif img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        encoding = "bgr8"
    else:
        raise ValueError(f"cannot encode image of shape {img.shape} and dtype {img.dtype}")
    h, w = img.shape[:2]
    return {
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": img.strides[0],
        "data": img.tobytes(),
    }
