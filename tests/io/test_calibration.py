"""Stereo calibration of a vehicle: CameraInfo, rig config, /tf_static, the rectified
projection; resolved once."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import CalibrationError
from cvslam_cli.geometry.rotations import make_T
from cvslam_cli.io.calibration import Calibration, StaticTransforms
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.topic_map import map_topics
from cvslam_cli.records.log import StereoFrame
from tests.synth import write_stereo_log

BASE = "logs.vehicles.uav1.rig"
CAM = "{width: 64, height: 48, fx: 50, fy: 50, cx: 32, cy: 24}"


def _calibration(path, overrides=()) -> Calibration:
    sources = [McapLogSource(path)]
    cfg = load_config(overrides=overrides).logs
    return Calibration(sources, map_topics(sources, cfg, "a.mcap"), cfg, "a.mcap")


def test_calibration_from_camera_info_and_tf_static(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", baseline_m=0.25)
    rig = _calibration(synth.path).rig("uav1")
    assert rig.left.source.startswith("CameraInfo") and "/tf_static" in rig.left.source
    assert rig.baseline_m == pytest.approx(0.25)
    assert rig.baseline_from_projection_m == pytest.approx(0.25)
    assert rig.rectified


def test_calibration_from_projection_when_no_tf(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", baseline_m=0.3, tf=False)
    rig = _calibration(synth.path).rig("uav1")
    assert rig.baseline_m == pytest.approx(0.3)
    assert "/tf_static" not in rig.left.source


def test_calibration_from_rig_config_when_no_camera_info(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", camera_info=False, tf=False)
    with pytest.raises(CalibrationError, match="no calibration for the left camera"):
        _calibration(synth.path).rig("uav1")
    right_T = "[1,0,0,0.12, 0,1,0,0, 0,0,1,0, 0,0,0,1]"
    overrides = [f"{BASE}.left={CAM}", f"{BASE}.right={CAM}", f"{BASE}.right.T_body_cam={right_T}"]
    logs = LogSet([McapLogSource(synth.path)], load_config(overrides=overrides).logs)
    rig = logs.rig("uav1")
    assert rig.left.source.startswith("config")
    assert rig.left.source == "config logs.vehicles.uav1.rig.left"
    assert rig.left.frame_id == "uav1/left_camera_optical"  # from the first image
    assert rig.baseline_m == pytest.approx(0.12)
    assert len([r for r in logs.records() if isinstance(r, StereoFrame)]) == 10


def test_zero_baseline_and_bad_focal_length_rejected(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", camera_info=False, tf=False)
    calib = _calibration(synth.path, [f"{BASE}.left={CAM}", f"{BASE}.right={CAM}"])
    with pytest.raises(
        CalibrationError, match=r"zero baseline.*/tf_static.*rig\.left\.T_body_cam and rig\.right"
    ):
        calib.rig("uav1")
    bad = "{width: 64, height: 48, fx: -5, fy: 50, cx: 32, cy: 24}"
    calib = _calibration(synth.path, [f"{BASE}.left={bad}", f"{BASE}.right={CAM}"])
    with pytest.raises(CalibrationError, match="non-positive focal length"):
        calib.rig("uav1")


def test_a_rig_is_resolved_once_and_so_is_its_error(tmp_path, monkeypatch):
    good = _calibration(write_stereo_log(tmp_path / "a.mcap").path)
    rig = good.rig("uav1")
    monkeypatch.setattr(good, "_first", lambda topic: pytest.fail(f"read {topic} again"))
    assert good.rig("uav1") is rig
    assert good.resolve(["uav1"]) == {"uav1": rig}
    synth = write_stereo_log(tmp_path / "b.mcap", camera_info=False, tf=False)
    bad = _calibration(synth.path)
    (error,) = bad.resolve(["uav1"]).values()
    assert isinstance(error, CalibrationError)
    monkeypatch.setattr(bad, "_first", lambda topic: pytest.fail(f"read {topic} again"))
    with pytest.raises(CalibrationError, match="no calibration for the left camera") as raised:
        bad.rig("uav1")
    assert raised.value is error


def test_static_transforms_chain_and_invert():
    tf = StaticTransforms()
    T_base_mount = make_T(np.eye(3), np.array([1.0, 0.0, 0.0]))
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T_mount_cam = make_T(R, np.array([0.0, 2.0, 0.0]))
    tf.add("base", "mount", T_base_mount)
    tf.add("mount", "cam", T_mount_cam)
    np.testing.assert_allclose(tf.lookup("/base", "cam"), T_base_mount @ T_mount_cam)
    np.testing.assert_allclose(
        tf.lookup("cam", "base"), np.linalg.inv(T_base_mount @ T_mount_cam), atol=1e-12
    )
    np.testing.assert_array_equal(tf.lookup("cam", "/cam"), np.eye(4))
    assert tf.lookup("base", "elsewhere") is None
