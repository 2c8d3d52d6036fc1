"""Every supported image encoding decodes to the expected array."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from cvslam_cli.io.images import ImageDecodeError, decode_compressed, decode_raw, raw_fields

RNG = np.random.default_rng(7)
GREY = RNG.integers(0, 256, size=(5, 7), dtype=np.uint8)
BGR = RNG.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)
DEEP = RNG.integers(0, 65536, size=(5, 7), dtype=np.uint16)


def _msg(arr, encoding, pad=0, big=False):
    h, w = arr.shape[:2]
    data = arr.astype(arr.dtype.newbyteorder(">" if big else "<")).tobytes()
    row = len(data) // h
    rows = [data[i * row : (i + 1) * row] + b"\0" * pad for i in range(h)]
    return SimpleNamespace(
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=int(big),
        step=row + pad,
        data=b"".join(rows),
    )


@pytest.mark.parametrize("pad", [0, 3])
def test_mono_and_colour_encodings(pad):
    np.testing.assert_array_equal(decode_raw(_msg(GREY, "mono8", pad))[0], GREY)
    np.testing.assert_array_equal(decode_raw(_msg(DEEP, "mono16", pad))[0], DEEP)
    np.testing.assert_array_equal(decode_raw(_msg(DEEP, "mono16", pad, big=True))[0], DEEP)
    np.testing.assert_array_equal(decode_raw(_msg(BGR, "bgr8", pad))[0], BGR)
    np.testing.assert_array_equal(decode_raw(_msg(BGR[:, :, ::-1].copy(), "rgb8", pad))[0], BGR)
    rgba = np.dstack([BGR[:, :, ::-1], np.full((5, 7), 200, np.uint8)])
    np.testing.assert_array_equal(decode_raw(_msg(rgba, "rgba8", pad))[0], BGR)
    bgra = np.dstack([BGR, np.full((5, 7), 9, np.uint8)])
    np.testing.assert_array_equal(decode_raw(_msg(bgra, "bgra8", pad))[0], BGR)


def test_unknown_encoding_and_short_data():
    with pytest.raises(ImageDecodeError, match="unknown image encoding 'nv21'"):
        decode_raw(_msg(GREY, "nv21"))
    short = _msg(GREY, "mono8")
    short.data = short.data[:-1]
    with pytest.raises(ImageDecodeError, match="expected 5 rows"):
        decode_raw(short)


def test_compressed_png_and_jpeg():
    ok, png = cv2.imencode(".png", GREY)
    assert ok
    out, _ = decode_compressed(SimpleNamespace(format="png", data=png.tobytes()))
    np.testing.assert_array_equal(out, GREY)
    yy, xx = np.mgrid[0:48, 0:64]
    big = np.dstack([xx * 4, yy * 5, 255 - xx * 3]).astype(np.uint8)  # smooth, distinct channels
    ok, jpg = cv2.imencode(".jpg", big, [cv2.IMWRITE_JPEG_QUALITY, 98])
    out, _ = decode_compressed(
        SimpleNamespace(format="bgr8; jpeg compressed bgr8", data=jpg.tobytes())
    )
    assert out.shape == (48, 64, 3)
    assert np.abs(out.astype(int) - big).mean() < 3  # channels not swapped
    out, _ = decode_compressed(
        SimpleNamespace(format="mono8; jpeg compressed mono8", data=jpg.tobytes())
    )
    assert out.ndim == 2
    with pytest.raises(ImageDecodeError, match="unknown compressed image format"):
        decode_compressed(SimpleNamespace(format="webp", data=b"x"))
    with pytest.raises(ImageDecodeError, match="could not be decoded"):
        decode_compressed(SimpleNamespace(format="png", data=b"not a png"))


def test_raw_fields_round_trip():
    for arr in (GREY, DEEP, BGR):
        f = raw_fields(arr)
        np.testing.assert_array_equal(decode_raw(SimpleNamespace(**f))[0], arr)


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_mosaics_demosaic_to_their_colour(pattern, bits):
    """A uniform colour mosaicked by `pattern` (its letters: the top-left 2x2 cell, row by
    row) comes back as that colour (B, G, R) inside the image."""
    bgr = {"b": 10, "g": 100, "r": 200}
    scale = 256 if bits == 16 else 1
    raw = np.zeros((8, 10), np.uint16 if bits == 16 else np.uint8)
    for k, ch in enumerate(pattern):
        raw[k // 2 :: 2, k % 2 :: 2] = bgr[ch] * scale
    out, enc = decode_raw(_msg(raw, f"bayer_{pattern}{bits}"))
    assert enc == f"bayer_{pattern}{bits}" and out.shape == (8, 10, 3) and out.dtype == raw.dtype
    np.testing.assert_array_equal(
        out[2:-2, 2:-2], np.broadcast_to(np.array([10, 100, 200]) * scale, (4, 6, 3))
    )


@pytest.mark.parametrize(
    ("encoding", "code"),
    [("yuv422", cv2.COLOR_BGR2YUV_UYVY), ("yuv422_yuy2", cv2.COLOR_BGR2YUV_YUY2)],
)
def test_yuv422_converts_to_bgr(encoding, code):
    flat = np.zeros((4, 6, 3), np.uint8)
    flat[:] = (60, 120, 180)
    yuv = cv2.cvtColor(flat, code)  # (H, W, 2)
    out, _ = decode_raw(_msg(yuv, encoding))
    assert out.shape == (4, 6, 3) and np.max(np.abs(out.astype(int) - flat)) <= 2


def test_16_bit_colour_keeps_its_depth_as_bgr():
    rgb16 = (BGR[:, :, ::-1].astype(np.uint16) * 257).copy()
    out, _ = decode_raw(_msg(rgb16, "rgb16", pad=2, big=True))
    np.testing.assert_array_equal(out, BGR.astype(np.uint16) * 257)
    bgra16 = np.dstack([BGR.astype(np.uint16) * 257, np.full(BGR.shape[:2], 7, np.uint16)])
    np.testing.assert_array_equal(
        decode_raw(_msg(bgra16, "bgra16"))[0], BGR.astype(np.uint16) * 257
    )
