"""Kalibr calibrations: a camchain-imucam.yaml written from EuRoC's published sensor.yaml
(T_cam_imu = inv(T_BS), T_cn_cnm1 = inv(T_BS1) T_BS0, computed here with numpy) gives the
rig the EuRoC importer reads from sensor.yaml, to 1e-9; `--calib` and `import kalibr` agree;
the time shift moves image stamps onto the IMU clock; radtan is plumb_bob."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cvslam_cli.config import load_config
from cvslam_cli.errors import CalibrationError
from cvslam_cli.io.calibration import camera_from_config
from cvslam_cli.io.importers.euroc import read_camera_yaml
from cvslam_cli.io.importers.kalibr import kalibr_config
from cvslam_cli.io.logs import open_logs
from cvslam_cli.records.log import StereoFrame
from tests.io.rosbag_fixtures import euroc_messages, write_ros1

SHIFT_S = 0.0012345


def _sensor(mav0: Path, cam: str) -> dict:
    return yaml.safe_load((mav0 / cam / "sensor.yaml").read_text().replace("%YAML:1.0", ""))


def _T_BS(d: dict) -> np.ndarray:
    return np.array(d["T_BS"]["data"], dtype=float).reshape(4, 4)


@pytest.fixture
def mav0(shared_data: Path) -> Path:
    path = shared_data / "euroc_v101_micro" / "mav0"
    if not path.is_dir():
        pytest.skip(f"{path} not found")
    return path


@pytest.fixture
def camchain(mav0: Path, tmp_path: Path) -> Path:
    """What `kalibr_calibrate_imu_camera` writes for EuRoC's cameras (IMU = body)."""
    s0, s1 = _sensor(mav0, "cam0"), _sensor(mav0, "cam1")
    T_cam0_imu, T_cam1_imu = np.linalg.inv(_T_BS(s0)), np.linalg.inv(_T_BS(s1))
    chain = {}
    for i, (s, T) in enumerate(((s0, T_cam0_imu), (s1, T_cam1_imu))):
        chain[f"cam{i}"] = {
            "T_cam_imu": T.tolist(),
            "camera_model": "pinhole",
            "distortion_coeffs": s["distortion_coefficients"],
            "distortion_model": "radtan",
            "intrinsics": s["intrinsics"],
            "resolution": s["resolution"],
            "rostopic": f"/cam{i}/image_raw",
            "timeshift_cam_imu": SHIFT_S,
        }
    chain["cam1"]["T_cn_cnm1"] = (T_cam1_imu @ np.linalg.inv(T_cam0_imu)).tolist()
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(yaml.safe_dump(chain))
    return path


@pytest.mark.realdata
def test_kalibr_gives_the_rig_of_euroc_sensor_yaml(mav0, camchain):
    cfg = load_config(layers=[("kalibr", kalibr_config(camchain, None))])
    rig = cfg.logs.vehicle_defaults.rig
    assert rig.camera_time_offset_ns == 1234500
    for side, cam in (("left", "cam0"), ("right", "cam1")):
        mine = camera_from_config(getattr(rig, side), "", "kalibr")
        ref = read_camera_yaml(mav0 / cam / "sensor.yaml", cam)
        assert mine.distortion_model == ref.distortion_model == "plumb_bob"
        assert (mine.width, mine.height) == (ref.width, ref.height) == (752, 480)
        assert np.allclose(mine.K, ref.K, atol=1e-9, rtol=0)
        assert np.allclose(np.r_[mine.D, 0.0], ref.D, atol=1e-9, rtol=0)
        assert np.allclose(mine.T_body_cam, ref.T_body_cam, atol=1e-9, rtol=0)


@pytest.mark.realdata
def test_import_kalibr_and_calib_option_agree(camchain, tmp_path, cvslam):
    out = tmp_path / "rig.yaml"
    res = cvslam("import", "kalibr", camchain, "-o", out, "--vehicle", "mav")
    assert res.code == 0, res.err
    from_file = load_config([out]).logs.vehicles["mav"]
    from_option = load_config(layers=[("k", kalibr_config(camchain, "mav"))]).logs.vehicles["mav"]
    assert from_file == from_option
    assert from_file.topics.left_image == "/cam0/image_raw"
    assert "T_body_cam = inv(T_cam_imu)" in out.read_text()
    res = cvslam("info", tmp_path / "nowhere.bag", "--calib", f"mav={tmp_path / 'missing.yaml'}")
    assert res.code == 1 and "missing.yaml" in res.err


@pytest.mark.realdata
def test_a_bag_without_camera_info_runs_on_the_kalibr_rig_and_clock(mav0, camchain, tmp_path):
    items = euroc_messages(mav0, 3, camera_info=False)
    bag = write_ros1(items, tmp_path / "v101.bag")
    plain = load_config().logs
    with pytest.raises(CalibrationError, match="no calibration for the left camera"):
        open_logs([bag], plain).rig("uav1")
    cfg = load_config(layers=[("k", kalibr_config(camchain, None))]).logs
    logs = open_logs([bag], cfg)
    assert logs.rig("uav1").describe()["baseline_m"] == pytest.approx(0.110, abs=2e-3)
    frames = [r for r in logs.records() if isinstance(r, StereoFrame)]
    image_stamps = sorted({i.log_time_ns for i in items if i.topic.endswith("left/image_raw")})
    assert [f.stamp_ns for f in frames] == [t + 1234500 for t in image_stamps]


def test_bad_kalibr_files_name_the_key(tmp_path):
    bad = tmp_path / "camchain.yaml"
    cam = {"camera_model": "pinhole", "intrinsics": [1, 1, 1, 1], "resolution": [2, 2]}
    cam1 = {**cam, "T_cn_cnm1": np.eye(4).tolist()}
    bad.write_text(yaml.safe_dump({"cam0": {**cam, "distortion_model": "fov"}, "cam1": cam1}))
    with pytest.raises(CalibrationError, match=r"cam0\.distortion_model: 'fov' is not supported"):
        kalibr_config(bad, None)
    bad.write_text(yaml.safe_dump({"cam0": cam}))
    with pytest.raises(CalibrationError, match="no cam1"):
        kalibr_config(bad, None)
    bad.write_text(yaml.safe_dump({"cam0": cam, "cam1": {**cam, "T_cn_cnm1": [[1, 2]]}}))
    with pytest.raises(CalibrationError, match=r"cam1\.T_cn_cnm1: expected a 4x4 matrix"):
        kalibr_config(bad, None)


def test_radtan_is_plumb_bob_in_the_config():
    cam = "{width: 64, height: 48, fx: 50, fy: 50, cx: 32, cy: 24, distortion_model: radtan}"
    cfg = load_config(overrides=[f"logs.vehicle_defaults.rig.left={cam}"])
    model = camera_from_config(cfg.logs.vehicle_defaults.rig.left, "", "config")
    assert model.distortion_model == "plumb_bob"
