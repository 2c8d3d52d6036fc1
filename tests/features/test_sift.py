"""Adaptive SIFT: the half-resolution base maps keypoints back exactly, the adaptive rule keeps
the keypoint count inside [features_min, features_max] where fixed SIFT does not (simulated
textures and real images), degenerate images give no keypoints."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from cvslam_cli.config import AdaptiveSiftConfig, SiftConfig
from cvslam_cli.features.sift import (
    DESCRIPTOR_SIZE,
    Keypoints,
    adaptive_parameters,
    detect_and_describe,
    dog_rms,
    select_spread,
    to_grey_u8,
)
from cvslam_cli.sim.texture import busy_texture, smooth_texture, to_uint8

W, H = 752, 480
SIFT = SiftConfig()
ADAPTIVE = AdaptiveSiftConfig()
FIXED = dataclasses.replace(ADAPTIVE, enabled=False)


def _blobs(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An image of isolated Gaussian blobs (bright and dark, sigma 2-9 px) at known sub-pixel
    positions on a grid; returns (uint8 image, (n, 3) x, y, sigma)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    img = np.full((H, W), 110.0)
    blobs = []
    step = 62
    for gy in range(45, H - 40, step):
        for gx in range(45, W - 40, step):
            x, y = gx + rng.uniform(-4, 4), gy + rng.uniform(-4, 4)
            s = rng.uniform(2.0, 9.0)
            img += (
                rng.choice([-1.0, 1.0])
                * 90.0
                * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * s * s))
            )
            blobs.append((x, y, s))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), np.array(blobs)


@pytest.mark.parametrize("half", [False, True])
def test_keypoints_land_on_the_blobs_in_both_modes(half: bool):
    img, blobs = _blobs()
    sift = dataclasses.replace(SIFT, half_resolution_base=half)
    kp, stats = detect_and_describe(img, sift, FIXED)
    assert len(kp) == stats.n_kept == stats.n_detected > 0
    d = np.linalg.norm(kp.uv_raw_px[:, None, :] - blobs[None, :, :2], axis=2)
    nearest, which = d.min(axis=1), d.argmin(axis=1)
    on_blob = nearest < 3.0
    assert on_blob.mean() > 0.9
    # nearly every blob is found (a few large ones lose to their neighbours' DoG), at its
    # full-resolution position to well within half a pixel
    assert np.unique(which[on_blob]).size >= 0.85 * len(blobs)
    err = kp.uv_raw_px[on_blob] - blobs[which[on_blob], :2]
    assert np.abs(err).max() < 0.5
    assert np.abs(err.mean(axis=0)).max() < 0.05  # no bias (the 0.25 px of imprecise upscaling)
    # size and octave refer to the original resolution: size / 2^octave = 2 sigma_kp / 2^o lies
    # in one octave's range [2 * 1.6, 2 * 3.2] (times 2^(+-0.5/s) for sub-layer interpolation)
    per_octave = kp.size_px / np.exp2(kp.octave.astype(np.float64))
    assert per_octave.min() > 3.2 * 2 ** (-0.5 / 3) * 0.99
    assert per_octave.max() < 6.4 * 2 ** (0.5 / 3) * 1.01
    assert kp.octave.min() >= (0 if half else -1)
    # the keypoint scale follows the blob's (a blob of sigma s peaks at sigma_kp ~ s)
    ratio = kp.size_px[on_blob] / 2 / blobs[which[on_blob], 2]
    assert 0.7 < np.median(ratio) < 1.4
    assert kp.desc.dtype == np.uint8 and kp.desc.shape == (len(kp), DESCRIPTOR_SIZE)


def test_full_resolution_fixed_mode_is_plain_opencv_sift():
    img, _ = _blobs(1)
    sift = dataclasses.replace(SIFT, half_resolution_base=False)
    kp, _ = detect_and_describe(img, sift, FIXED)
    ref = cv2.SIFT_create(0, 3, 0.04, 10.0, 1.6, cv2.CV_32F, True)
    kps, desc = ref.detectAndCompute(img, None)
    np.testing.assert_array_equal(kp.uv_raw_px, cv2.KeyPoint_convert(kps))
    np.testing.assert_array_equal(kp.desc.astype(np.float32), desc)  # integer-valued floats
    np.testing.assert_array_equal(kp.response, [k.response for k in kps])
    np.testing.assert_array_equal(kp.octave, [np.int8(k.octave & 255) for k in kps])


def test_dog_rms_measures_contrast():
    img, _ = _blobs()
    r = dog_rms(img)
    assert r > 0
    half_contrast = (img.astype(np.float64) - 110.0) * 0.5 + 110.0
    assert dog_rms(np.rint(half_contrast).astype(np.uint8)) == pytest.approx(r / 2, rel=0.05)
    assert dog_rms(np.full((H, W), 77, np.uint8)) == 0.0
    assert dog_rms(np.zeros((0, 0), np.uint8)) == 0.0


def test_inputs_are_converted_to_grey_uint8():
    img, _ = _blobs()
    base, _ = detect_and_describe(img, SIFT, ADAPTIVE)
    as_u16, _ = detect_and_describe(img.astype(np.uint16) << 8, SIFT, ADAPTIVE)
    as_12bit, _ = detect_and_describe(img.astype(np.uint16) << 4, SIFT, ADAPTIVE)
    as_bgr, _ = detect_and_describe(np.dstack([img, img, img]), SIFT, ADAPTIVE)
    for other in (as_u16, as_12bit, as_bgr):
        np.testing.assert_array_equal(other.uv_raw_px, base.uv_raw_px)
        np.testing.assert_array_equal(other.desc, base.desc)
    np.testing.assert_array_equal(to_grey_u8(img.astype(np.float32) / 255.0), img)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((0, 0), np.uint8),
        np.zeros((H, W), np.uint8),
        np.full((H, W), 200, np.uint8),
        np.full((H, W, 3), 90, np.uint8),
        np.full((5, 3), 1, np.uint8),
    ],
    ids=["empty", "black", "constant", "constant-colour", "tiny"],
)
@pytest.mark.parametrize("adaptive", [ADAPTIVE, FIXED], ids=["adaptive", "fixed"])
def test_degenerate_images_give_no_keypoints(image: np.ndarray, adaptive: AdaptiveSiftConfig):
    kp, stats = detect_and_describe(image, SIFT, adaptive)
    assert len(kp) == 0 and stats.n_kept == 0
    assert kp.uv_raw_px.shape == (0, 2) and kp.desc.shape == (0, DESCRIPTOR_SIZE)
    assert kp.octave.dtype == np.int32 and kp.desc.dtype == np.uint8
    assert len(Keypoints.empty()) == 0


# -- the adaptive rule ---------------------------------------------------------------------


def test_rule_adds_layers_and_lowers_the_threshold_for_weak_dog_energy():
    s_ref, c_ref = adaptive_parameters(ADAPTIVE.dog_rms_ref, SIFT, ADAPTIVE)
    assert s_ref == SIFT.n_octave_layers
    # effective DoG threshold = contrast_per_rms * rms at the reference spacing
    assert c_ref / s_ref == pytest.approx(ADAPTIVE.contrast_per_rms * ADAPTIVE.dog_rms_ref)
    s_weak, c_weak = adaptive_parameters(ADAPTIVE.dog_rms_ref / 4, SIFT, ADAPTIVE)
    assert s_weak == SIFT.n_octave_layers + 2 and c_weak < c_ref
    s_busy, _ = adaptive_parameters(ADAPTIVE.dog_rms_ref * 2, SIFT, ADAPTIVE)
    assert s_busy == SIFT.n_octave_layers - 1
    assert adaptive_parameters(1e-9, SIFT, ADAPTIVE)[0] == ADAPTIVE.layers_max
    assert adaptive_parameters(1.0, SIFT, ADAPTIVE) == (ADAPTIVE.layers_min, ADAPTIVE.contrast_max)


@pytest.fixture(scope="module")
def textures() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(42)
    return {
        "smooth": to_uint8(smooth_texture((H, W), rng, px_per_m=4.0)),
        "busy": to_uint8(busy_texture((H, W), rng, px_per_m=1.5)),
    }


def _in_range(n: int) -> bool:
    return ADAPTIVE.features_min <= n <= ADAPTIVE.features_max


def test_adaptive_count_in_range_where_fixed_sift_is_not(textures):
    counts = {}
    for name, img in textures.items():
        fixed, _ = detect_and_describe(img, SIFT, FIXED)
        adaptive, stats = detect_and_describe(img, SIFT, ADAPTIVE)
        counts[name] = (len(fixed), len(adaptive), stats)
        print(
            f"{name}: dog_rms {stats.dog_rms:.4f}, fixed SIFT {len(fixed)} keypoints, adaptive "
            f"{len(adaptive)} (s={stats.n_octave_layers}, contrast {stats.contrast_threshold:.4f})"
        )
        assert _in_range(len(adaptive))
    assert counts["smooth"][0] < ADAPTIVE.features_min
    assert counts["busy"][0] > ADAPTIVE.features_max
    # the smooth image got finer scale sampling than the busy one
    assert counts["smooth"][2].n_octave_layers > counts["busy"][2].n_octave_layers


def test_retry_and_cap(textures):
    img = textures["busy"]
    capped = dataclasses.replace(ADAPTIVE, features_max=200)
    kp, stats = detect_and_describe(img, SIFT, capped)
    assert stats.n_detected > 200 and len(kp) == stats.n_kept == 200
    # the kept ones cover the image: every grid cell that had keypoints keeps at least one
    full, _ = detect_and_describe(img, SIFT, dataclasses.replace(ADAPTIVE, features_max=10**6))

    def cells(uv: np.ndarray) -> set[tuple[int, int]]:
        return set(map(tuple, (uv // np.array([W / 8, H / 6])).astype(int).tolist()))

    assert len(cells(kp.uv_raw_px)) >= 0.9 * len(cells(full.uv_raw_px))
    # and the strongest are kept: their median response exceeds that of all detected
    assert np.median(kp.response) > np.median(full.response)

    greedy = dataclasses.replace(ADAPTIVE, features_min=10**6, features_max=10**7)
    kp2, stats2 = detect_and_describe(textures["smooth"], SIFT, greedy)
    _, first = detect_and_describe(textures["smooth"], SIFT, ADAPTIVE)
    assert stats2.retried and not first.retried
    assert stats2.contrast_threshold == pytest.approx(
        max(first.contrast_threshold * ADAPTIVE.retry_factor, ADAPTIVE.contrast_min)
    )
    assert len(kp2) > first.n_kept


def test_select_spread_round_robin():
    uv = np.array([[1, 1], [2, 2], [3, 3], [90, 90]], np.float32)
    response = np.array([0.5, 0.9, 0.1, 0.01], np.float32)
    # 2 cells (100 x 50 image, 2 cells): the best of the crowded cell, then the lone one
    np.testing.assert_array_equal(select_spread(uv, response, 100, 50, 2, cells=2), [1, 3])
    np.testing.assert_array_equal(select_spread(uv, response, 100, 50, 3, cells=2), [0, 1, 3])
    np.testing.assert_array_equal(select_spread(uv, response, 100, 50, 9, cells=2), [0, 1, 2, 3])


# -- real images ---------------------------------------------------------------------------


def _real_images(shared_data: Path) -> dict[str, list[Path]]:
    sets = {
        "euroc": shared_data / "euroc_v101_micro/mav0/cam0/data",
        "kitti": shared_data / "kitti_clip_a/image_l",
    }
    out = {}
    for name, folder in sets.items():
        files = sorted(folder.glob("*.png"))
        if not files:
            pytest.skip(f"{folder} holds no images")
        out[name] = [files[i] for i in (0, len(files) // 2, len(files) - 1)]
    return out


@pytest.mark.realdata
def test_adaptive_count_in_range_on_real_images(shared_data: Path):
    for name, files in _real_images(shared_data).items():
        for path in files:
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            kp, stats = detect_and_describe(img, SIFT, ADAPTIVE)
            fixed, _ = detect_and_describe(img, SIFT, FIXED)
            print(
                f"{name} {path.name}: dog_rms {stats.dog_rms:.4f} s={stats.n_octave_layers} "
                f"contrast {stats.contrast_threshold:.4f}: {len(kp)} keypoints "
                f"(fixed SIFT {len(fixed)}), {1e3 * (stats.detect_s + stats.describe_s):.0f} ms"
            )
            assert _in_range(len(kp))
            h, w = img.shape[:2]
            assert np.all((kp.uv_raw_px >= 0) & (kp.uv_raw_px <= [w - 1, h - 1]))
