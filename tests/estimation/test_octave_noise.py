"""The bearing noise by octave (`octave_noise.py`): octave o takes the o-th factor (octaves
beyond the list its last, below 0 its first), and a run whose stereo matches all get a
factor of 1 (the landmark-mode simulator's keypoints, all at octave 0) is left as it is."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.octave_noise import AUTO_FACTORS, OctaveBearingNoise, resolve


def test_each_octave_takes_its_factor() -> None:
    noise = OctaveBearingNoise.of([1.0, 3.0, 5.0], [np.array([0, 1]), np.array([4])])
    assert noise is not None
    np.testing.assert_array_equal(
        noise.scale(np.array([-1, 0, 1, 2, 3, 9])), [1.0, 1.0, 3.0, 5.0, 5.0, 5.0]
    )


def test_factors_of_one_for_every_match_leave_the_noise_alone() -> None:
    assert OctaveBearingNoise.of([], [np.arange(4)]) is None
    assert OctaveBearingNoise.of([1.0], [np.arange(4)]) is None
    # every keypoint at octave 0 (the landmark-mode simulator's)
    assert OctaveBearingNoise.of([1.0, 3.0, 5.0], [np.zeros(50, np.int64)]) is None
    assert OctaveBearingNoise.of([1.0, 1.0, 2.0], [np.array([0, 1, 1]), np.array([-1])]) is None
    assert OctaveBearingNoise.of([2.0], [np.zeros(3, np.int64)]) is not None


def test_auto_scales_the_octaves_when_every_vehicle_has_an_imu() -> None:
    assert resolve("auto", ["ins", "ins"]) == (AUTO_FACTORS, "auto: a vehicle has an IMU")
    assert resolve("auto", ["ins", "odometry"])[0] == AUTO_FACTORS  # a mixed team
    assert resolve("auto", ["odometry", "odometry"])[0] == ()
    assert resolve("auto", ["constant_velocity"])[0] == ()
    assert resolve((1.0, 2.0), ["odometry"])[0] == (1.0, 2.0)
    assert resolve((), ["ins"])[0] == ()
    assert AUTO_FACTORS[0] == 1.0  # the finest keypoints keep the measured noise
