"""The keypoints' pixel noise measured from the frames' own motion (features/pixel_noise.py,
`fuse.association.pixel_sigma_px: auto`): the noise itself where it is Gaussian, above the
core where the tail is heavy, nothing from a rig that is not rectified."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.features.frame_pairs import RectifiedIntrinsics, moved, predicted_uvd
from cvslam_cli.features.pixel_noise import (
    pixel_noise,
    prediction_jacobian,
    sample_pixel_noise,
)
from tests.features.synthetic_frames import frames_of, rig, skewed_rig


@pytest.mark.parametrize(
    ("ahead", "noise_px"), [(True, 0.3), (True, 0.5), (False, 0.2), (False, 0.3)]
)
def test_gaussian_noise_is_measured(ahead, noise_px):
    """Gaussian pixel noise ahead of a car (depths 3-120 m: the earlier frame's depth noise
    moves the prediction much) and over ground 60 m below (a sideways step and a turn look
    alike there: the motion must be fitted to the whitened residuals): found within 6 %, and
    the core (median-based) agrees with the tail-matched sigma."""
    fs, _ = frames_of(0.0, ahead=ahead, noise_px=noise_px, frames=8)
    sample = sample_pixel_noise(fs, rig())
    assert sample.pairs == fs.n_frames - 1 and sample.points > 2000
    noise = pixel_noise([sample])
    assert noise is not None
    assert noise.sigma_px == pytest.approx(noise_px, rel=0.06)
    assert noise.core_sigma_px == pytest.approx(noise_px, rel=0.06)


@pytest.mark.parametrize("ahead", [True, False])
def test_a_heavy_tail_raises_the_sigma_above_the_core(ahead):
    """5 % of the pixel coordinates at 1.5 px, the rest at 0.2 px (SIFT-like): the core
    stays near 0.2 px; the sigma the filter gets covers the tail, at least 1.6x the core."""
    fs, _ = frames_of(0.0, ahead=ahead, noise_px=0.2, tail_share=0.05, tail_px=1.5, frames=8)
    noise = pixel_noise([sample_pixel_noise(fs, rig())])
    assert noise is not None
    assert noise.core_sigma_px == pytest.approx(0.2, rel=0.2)
    assert noise.sigma_px > 1.6 * noise.core_sigma_px


def test_prediction_jacobian_equals_finite_differences():
    rng = np.random.default_rng(3)
    K = RectifiedIntrinsics.of(rig())
    uvd0 = np.column_stack(
        [rng.uniform(100, 1100, 20), rng.uniform(50, 300, 20), rng.uniform(3, 60, 20)]
    )
    motion = np.array([0.01, -0.02, 0.005, 0.1, -0.05, -1.2])
    J = prediction_jacobian(uvd0, motion, K)
    h = 1e-6
    for c in range(3):
        d = np.zeros(3)
        d[c] = h
        fd = (
            predicted_uvd(moved(uvd0 + d, motion, K), K)
            - predicted_uvd(moved(uvd0 - d, motion, K), K)
        ) / (2 * h)
        np.testing.assert_allclose(J[:, :, c], fd, rtol=1e-5, atol=1e-6)


def test_nothing_measured_without_a_rectified_rig_or_enough_frames():
    fs, _ = frames_of(0.0, ahead=True, frames=1)
    assert sample_pixel_noise(fs, rig()).points == 0
    skew = skewed_rig()
    fs, _ = frames_of(0.0, ahead=True, frames=3)
    sample = sample_pixel_noise(fs, skew)
    assert sample.points == 0 and sample.pairs == 0
    assert pixel_noise([sample]) is None
    assert pixel_noise([]) is None
