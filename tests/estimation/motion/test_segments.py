"""Motion samples between frames: zero-order hold."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.motion.segments import motion_segments


def test_motion_segments_hold_each_sample_until_the_next():
    stamps = np.array([0, 10, 20, 30], dtype=np.int64) * 1_000_000
    U = np.arange(4, dtype=float)[:, None] * np.ones((1, 2))
    u, dts = motion_segments(stamps, U, 5_000_000, 25_000_000)
    np.testing.assert_allclose(dts, [5e-3, 10e-3, 5e-3])
    np.testing.assert_allclose(u[:, 0], [0, 1, 2])
    u, dts = motion_segments(stamps, U, 0, 0)
    assert len(dts) == 0
    # before the first sample: the first one; no samples (constant velocity): one step
    u, dts = motion_segments(stamps, U, -5_000_000, 5_000_000)
    np.testing.assert_allclose(u[:, 0], [0, 0])
    u, dts = motion_segments(np.zeros(0, dtype=np.int64), np.zeros((0, 0)), 0, 100_000_000)
    assert u.shape == (1, 0) and np.allclose(dts, [0.1])
