"""Camera models and the stereo rig: to and from the feature files' calibration record."""

from __future__ import annotations

import numpy as np

from cvslam_cli.geometry.camera import rig_calibration, stereo_rig
from tests.synth import feature_rig


def test_rig_calibration_round_trips_through_the_stereo_rig():
    rig = feature_rig()
    back = rig_calibration(stereo_rig(rig))
    for name in ("K", "D", "T_body_cam", "size_px"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rig, name), err_msg=name)
