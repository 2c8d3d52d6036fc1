"""Motion samples between frames: each piece driven by the samples interpolated at its
midpoint."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.motion.segments import motion_segments


def test_each_piece_is_driven_by_the_samples_at_its_midpoint():
    stamps = np.array([0, 10, 20, 30], dtype=np.int64) * 1_000_000
    U = np.arange(4, dtype=float)[:, None] * np.array([[1.0, -2.0]])
    u, dts = motion_segments(stamps, U, 5_000_000, 25_000_000)
    np.testing.assert_allclose(dts, [5e-3, 10e-3, 5e-3])
    # (5, 10) ms: the line through samples 0 and 1 at 7.5 ms; a whole interval: the mean
    np.testing.assert_allclose(u, [[0.75, -1.5], [1.5, -3.0], [2.25, -4.5]])
    u, dts = motion_segments(stamps, U, 0, 0)
    assert len(dts) == 0
    # before the first sample the first, after the last the last
    u, dts = motion_segments(stamps, U, -5_000_000, 5_000_000)
    np.testing.assert_allclose(u[:, 0], [0, 0.25])
    u, dts = motion_segments(stamps, U, 25_000_000, 45_000_000)
    np.testing.assert_allclose(u[:, 0], [2.75, 3.0])
    np.testing.assert_allclose(dts, [5e-3, 15e-3])
    # no samples (constant velocity): one step
    u, dts = motion_segments(np.zeros(0, dtype=np.int64), np.zeros((0, 0)), 0, 100_000_000)
    assert u.shape == (1, 0) and np.allclose(dts, [0.1])


def test_stamps_since_the_epoch_interpolate_as_exactly_as_small_ones():
    """Nanosecond stamps of ~1.7e18 (a recorded log) give the same inputs as the same
    samples at small stamps: the interpolation works on times relative to the piece."""
    base = 1_733_500_000_123_456_789
    stamps = np.arange(0, 50_000_000, 5_000_000, dtype=np.int64)
    U = np.random.default_rng(3).normal(size=(len(stamps), 6))
    small = motion_segments(stamps, U, 7_000_000, 31_000_000)
    large = motion_segments(stamps + base, U, base + 7_000_000, base + 31_000_000)
    np.testing.assert_allclose(large[0], small[0], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(large[1], small[1])


def test_the_exact_imu_integrates_closer_to_the_truth_than_with_each_sample_held():
    """A level UAV entering a turn (yaw rate ramping up to 0.5 rad/s), IMU samples at 200 Hz
    of the exact motion: the INS model stepped over the pieces ends nearer the true heading
    (the rate's integral) than with each sample held over its interval (by half a sample
    of the rate's growth per step: 1.25 mrad here)."""
    from cvslam_cli.estimation.motion.ins import InsNoise
    from cvslam_cli.estimation.motion.models import InsModel, propagate

    rate_hz, T = 200.0, 4.0
    t = np.arange(0.0, T + 1e-9, 1 / rate_hz)
    yaw_rate = 0.5 * np.sin(0.5 * np.pi * t / T) ** 2  # 0 -> 0.5 rad/s
    true_yaw = 0.5 * (0.5 * T - T / (2 * np.pi) * np.sin(np.pi * T / T))  # its integral
    gyro = np.stack([np.zeros_like(t), np.zeros_like(t), yaw_rate], axis=1)
    accel = np.tile([0.0, 0.0, -9.80665], (len(t), 1))  # level, no acceleration: hovering
    U = np.concatenate([accel, gyro], axis=1)
    stamps = np.round(t * 1e9).astype(np.int64)
    model = InsModel(InsNoise(0.002, 0.00017), biases=False)
    x0 = np.zeros(9)
    u, dts = motion_segments(stamps, U, 0, stamps[-1])
    x_mid, _, _ = propagate(model, x0, u, dts)
    x_held, _, _ = propagate(model, x0, U[:-1], np.diff(stamps) * 1e-9)
    assert abs(x_held[8] - true_yaw) > 1e-3
    assert abs(x_mid[8] - true_yaw) < 1e-5
