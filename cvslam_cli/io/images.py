"""Image decoding/encoding for sensor_msgs/msg/Image and sensor_msgs/msg/CompressedImage.

Decoded images are numpy arrays: (H, W) for mono encodings (uint8 or uint16), (H, W, 3)
BGR uint8 for colour (alpha dropped), which is what OpenCV expects downstream.
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
    if encoding == "rgb8":
        arr = arr[:, :, ::-1]
    elif encoding == "rgba8":
        arr = cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGBA2BGR)
    elif encoding == "bgra8":
        arr = cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_BGRA2BGR)
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
