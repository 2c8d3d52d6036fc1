"""A Kalibr camera-chain calibration (`camchain-imucam.yaml` or `camchain.yaml`) as a rig config.

Kalibr writes, per camera `camN`: `camera_model` (pinhole), `intrinsics` [fu, fv, pu, pv],
`distortion_model` (radtan: k1 k2 r1 r2, i.e. ROS plumb_bob without k3; equidistant: k1..k4),
`distortion_coeffs`, `resolution` [w, h], `rostopic`, and, from an IMU-camera calibration,
`T_cam_imu` (4x4, maps IMU-frame points into the camera frame) and `timeshift_cam_imu` (s, with
t_imu = t_cam + shift); from the second camera on, `T_cn_cnm1` (maps camera n-1's frame into
camera n's).

The rig's body frame is the IMU frame when `T_cam_imu` is given (T_body_cam = inv(T_cam_imu)),
else cam0's frame (T_body_cam0 = I). The right camera's pose comes from the chain, which is the
stereo calibration itself: T_body_cam1 = T_body_cam0 inv(T_cn_cnm1); with no `T_cn_cnm1`, from
its own `T_cam_imu`. The time shift becomes `rig.camera_time_offset_ns`, added to image stamps
to put them on the IMU's clock.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cvslam_cli.errors import CalibrationError
from cvslam_cli.geometry.rotations import invert_T, is_rotation
from cvslam_cli.io.textfiles import read_yaml_mapping
from cvslam_cli.records.arrays import F64

_MODELS = {"radtan": "plumb_bob", "equidistant": "equidistant", "none": "none"}
_N_COEFFS = {"radtan": 4, "equidistant": 4, "none": 0}


def _matrix(path: Path, cam: str, key: str, raw: Any) -> F64:
    try:
        T = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise CalibrationError(f"{path}: {cam}.{key}: expected a 4x4 matrix of numbers")
    if not (is_rotation(T[:3, :3], 1e-6) and np.allclose(T[3], [0, 0, 0, 1])):
        raise CalibrationError(
            f"{path}: {cam}.{key}: expected a rigid transform (rotation, translation, "
            "last row 0 0 0 1)"
        )
    return T


def _numbers(path: Path, cam: str, key: str, raw: Any, n: int) -> list[float]:
    ok = isinstance(raw, list) and len(raw) == n
    vals = [float(x) for x in raw] if ok and all(isinstance(x, (int, float)) for x in raw) else []
    if len(vals) != n or not np.all(np.isfinite(vals)):
        raise CalibrationError(f"{path}: {cam}.{key}: expected {n} numbers, got {raw!r}")
    return vals


def _camera(path: Path, name: str, c: Any, T_body_cam: F64) -> dict[str, Any]:
    """One camera of the chain as a `logs.vehicles.<v>.rig.<side>` mapping."""
    if not isinstance(c, dict):
        raise CalibrationError(f"{path}: {name}: expected a mapping")
    model = c.get("camera_model", "pinhole")
    if model != "pinhole":
        raise CalibrationError(
            f"{path}: {name}.camera_model: {model!r} is not supported (pinhole only)"
        )
    dist = c.get("distortion_model", "none")
    if dist not in _MODELS:
        raise CalibrationError(
            f"{path}: {name}.distortion_model: {dist!r} is not supported "
            f"(expected one of {', '.join(_MODELS)})"
        )
    fx, fy, cx, cy = _numbers(path, name, "intrinsics", c.get("intrinsics"), 4)
    w, h = _numbers(path, name, "resolution", c.get("resolution"), 2)
    coeffs = _numbers(
        path, name, "distortion_coeffs", c.get("distortion_coeffs", []), _N_COEFFS[dist]
    )
    return {
        "width": int(w),
        "height": int(h),
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "distortion_model": _MODELS[dist],
        "distortion": coeffs,
        "T_body_cam": [float(x) for x in T_body_cam.reshape(-1)],
    }


def kalibr_rig(path: Path) -> tuple[dict[str, Any], dict[str, str], str]:
    """(rig mapping with left/right cameras and camera_time_offset_ns, image topics by role,
    a note saying what the body frame is) of the Kalibr file at `path`; CalibrationError
    naming the file and key for anything it cannot use."""
    data = read_yaml_mapping(path, "a Kalibr camchain YAML", CalibrationError)
    for cam in ("cam0", "cam1"):
        if cam not in data:
            raise CalibrationError(
                f"{path}: no {cam} (a Kalibr camchain of a stereo pair has cam0 and cam1)"
            )
    c0, c1 = data["cam0"], data["cam1"]
    if isinstance(c0, dict) and "T_cam_imu" in c0:
        T_body_cam0 = invert_T(_matrix(path, "cam0", "T_cam_imu", c0["T_cam_imu"]))
        note = "body frame = the IMU frame (T_body_cam = inv(T_cam_imu))"
    else:
        T_body_cam0 = np.eye(4)
        note = "body frame = cam0's frame (the file has no T_cam_imu)"
    if isinstance(c1, dict) and "T_cn_cnm1" in c1:
        T_body_cam1 = T_body_cam0 @ invert_T(_matrix(path, "cam1", "T_cn_cnm1", c1["T_cn_cnm1"]))
    elif isinstance(c1, dict) and "T_cam_imu" in c1 and "T_cam_imu" in c0:
        T_body_cam1 = invert_T(_matrix(path, "cam1", "T_cam_imu", c1["T_cam_imu"]))
    else:
        raise CalibrationError(f"{path}: cam1 has neither T_cn_cnm1 nor T_cam_imu")
    rig: dict[str, Any] = {
        "left": _camera(path, "cam0", c0, T_body_cam0),
        "right": _camera(path, "cam1", c1, T_body_cam1),
    }
    shift = c0.get("timeshift_cam_imu", 0.0)
    if not isinstance(shift, (int, float)) or not np.isfinite(shift):
        raise CalibrationError(f"{path}: cam0.timeshift_cam_imu: expected a number of seconds")
    rig["camera_time_offset_ns"] = round(float(shift) * 1e9)
    topics = {
        role: str(c["rostopic"])
        for role, c in (("left_image", c0), ("right_image", c1))
        if isinstance(c.get("rostopic"), str)
    }
    return rig, topics, note


def kalibr_config(path: Path, vehicle: str | None) -> dict[str, Any]:
    """The config layer of a Kalibr file: the rig of `vehicle` (logs.vehicles.<vehicle>,
    with the image topics Kalibr calibrated on), or of every vehicle (logs.vehicle_defaults,
    rig only: topic templates keep their `{vehicle}`)."""
    rig, topics, _ = kalibr_rig(path)
    if vehicle is None:
        return {"logs": {"vehicle_defaults": {"rig": rig}}}
    entry: dict[str, Any] = {"rig": rig}
    if topics:
        entry["topics"] = topics
    return {"logs": {"vehicles": {vehicle: entry}}}


def kalibr_config_text(path: Path, vehicle: str | None) -> str:
    """`kalibr_config` as a commented YAML config file (`cvslam import kalibr`)."""
    _, _, note = kalibr_rig(path)
    head = (
        f"# From the Kalibr calibration {path}: {note}; cam0 -> left, cam1 -> right "
        "(T_body_cam1 from T_cn_cnm1); radtan -> plumb_bob; timeshift_cam_imu -> "
        "rig.camera_time_offset_ns.\n# Use with --config FILE.\n"
    )
    return head + yaml.safe_dump(kalibr_config(path, vehicle), sort_keys=False)
