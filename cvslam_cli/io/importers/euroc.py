"""EuRoC MAV dataset (ASL folder layout) -> cvslam MCAP log.

Layout read (`mav0/`): `cam0/` (left) and `cam1/` (right), each with `data.csv`
(timestamp [ns], filename), `data/*.png` and `sensor.yaml` (OpenCV YAML: `T_BS` body<-sensor,
`resolution` [w, h], `intrinsics` [fu, fv, cu, cv], `distortion_model`,
`distortion_coefficients`); `imu0/data.csv` (timestamp [ns], w_RS_S xyz [rad/s],
a_RS_S xyz [m/s^2]) with `imu0/sensor.yaml` (noise densities); optional ground truth in
`state_groundtruth_estimate0/data.csv` (raw EuRoC: timestamp [ns], p_RS_R xyz [m],
q_RS wxyz, ...) or `state_groundtruth_estimate0/groundtruth.tum` (t [s] x y z qx qy qz qw).

Frames: the body frame is EuRoC's body frame, i.e. the IMU (imu0 `T_BS` = identity); it is
NOT re-oriented to FRD. Cameras are unrectified (radial-tangential -> ROS "plumb_bob",
D = [k1, k2, p1, p2, 0], R = I, P = [K | 0]) with `T_body_cam` = the camera's `T_BS`.
The ground truth's world frame R (Vicon, z up) is converted to NED with
`R_NED_WORLD` (world x -> east, world y -> north, world z -> up = -down), origin unchanged:
p_nav = R_NED_WORLD p_world, C_nav_body = R_NED_WORLD C_world_body.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from cvslam_cli.errors import DatasetError
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.output_frames import DatasetFrame
from cvslam_cli.geometry.rotations import (
    is_rotation,
    make_T,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
)
from cvslam_cli.io.importers.common import (
    ImportPlan,
    ImportSummary,
    ImuTable,
    StereoFiles,
    check_rig,
    check_vehicle_name,
    import_metadata,
    read_stamped_csv,
    require_dir,
    require_file,
    rig_metadata,
    write_plan,
)
from cvslam_cli.io.textfiles import (
    check_stamps_increasing,
    data_lines,
    read_text,
    read_yaml_mapping,
)
from cvslam_cli.io.trajectory import first_non_unit, read_tum
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.poses import PoseTable

#: Rotation from the EuRoC Vicon world frame (z up) to NED: world x -> east, y -> north,
#: z -> up (= -down). A proper rotation (det +1).
R_NED_WORLD: F64 = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

CONVERSION = (
    "Ground truth (EuRoC state_groundtruth_estimate0, pose of the IMU body frame in the Vicon "
    "world frame R, z up) was rotated to NED with R_ned_world = [[0,1,0],[1,0,0],[0,0,-1]] "
    "(world x -> east, world y -> north, world z -> up), origin unchanged: "
    "p_nav = R_ned_world p_world, C_nav_body = R_ned_world C_world_body. The body frame "
    "(<vehicle>/base_link) is EuRoC's IMU body frame (imu0, T_BS = identity), not re-oriented "
    "to FRD; camera extrinsics T_body_cam are cam0/cam1 T_BS; IMU samples are in the body frame."
)

#: EuRoC's own frame: the pose of the IMU body (the vehicle's body frame) in the Vicon world.
DATASET_FRAME = DatasetFrame(
    make_T(R_NED_WORLD, np.zeros(3)),
    np.eye(4),
    "EuRoC Vicon world frame R (z up)",
    "imu0 body frame B (EuRoC's body frame)",
)

_DISTORTION = {"radial-tangential": "plumb_bob", "equidistant": "equidistant"}


def import_euroc(
    mav0_dir: Path, out_path: Path, vehicle: str, *, progress: bool = False
) -> ImportSummary:
    """Import a EuRoC `mav0` folder (or the folder holding it) into the MCAP log `out_path`
    for vehicle `vehicle`. Raises `DatasetError` naming the file for any bad input; on error
    no output file is left behind."""
    plan = plan_euroc(Path(mav0_dir), vehicle)
    return write_plan(plan, Path(out_path), progress=progress, desc=f"euroc {vehicle}")


def plan_euroc(mav0_dir: Path, vehicle: str) -> ImportPlan:
    """Read and check everything but the image pixels; see the module docstring."""
    names = check_vehicle_name(vehicle)
    require_dir(mav0_dir, "a EuRoC mav0 folder (cam0/, cam1/, imu0/)")
    if not (mav0_dir / "cam0").exists() and (mav0_dir / "mav0").is_dir():
        mav0_dir = mav0_dir / "mav0"
    notes: list[str] = []
    cams: list[CameraModel] = []
    tables: list[tuple[I64, list[Path]]] = []
    for cam_dir, frame_id in (("cam0", names.left_frame), ("cam1", names.right_frame)):
        d = require_dir(mav0_dir / cam_dir, f"the EuRoC camera folder {cam_dir}/")
        cams.append(read_camera_yaml(d / "sensor.yaml", frame_id))
        tables.append(read_image_csv(d / "data.csv", d / "data"))
    rig = StereoRig(cams[0], cams[1])
    check_rig(rig, f"{mav0_dir / 'cam0' / 'sensor.yaml'} + {mav0_dir / 'cam1' / 'sensor.yaml'}")
    frames, pair_notes = pair_by_stamp(tables[0], tables[1], mav0_dir)
    notes += pair_notes

    imu, imu_meta, imu_notes = read_imu(mav0_dir / "imu0")
    notes += imu_notes
    gt, gt_source = read_ground_truth(mav0_dir / "state_groundtruth_estimate0")
    if gt is not None:
        notes.append(f"ground truth from {Path(gt_source).relative_to(mav0_dir)}")
    else:
        notes.append("no ground truth (no state_groundtruth_estimate0/data.csv or groundtruth.tum)")

    metadata = {
        "cvslam.import": import_metadata(
            "euroc",
            mav0_dir,
            vehicle,
            CONVERSION,
            "EuRoC IMU body frame (imu0)",
            Path(gt_source) if gt is not None else None,
            DATASET_FRAME,
        ),
        "cvslam.rig": rig_metadata(names, rig, imu=json.dumps(imu_meta)),
    }
    return ImportPlan(names, rig, frames, imu, gt, metadata, tuple(notes))


# --------------------------------------------------------------------------- cameras


def _numbers(
    data: dict[str, Any], key: str, n: int | None, path: Path, expected: str
) -> list[float]:
    value = data.get(key)
    if isinstance(value, dict) and "data" in value:  # OpenCV matrix {rows, cols, data}
        value = value["data"]
    ok = (
        isinstance(value, list)
        and (n is None or len(value) == n)
        and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
            for v in value
        )
    )
    if not ok:
        shown = "nothing" if value is None else repr(value)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise DatasetError(f"{path}: {key}: expected {expected}, got {shown}")
    return [float(v) for v in value]


def read_T_BS(data: dict[str, Any], path: Path) -> F64:
    """`T_BS` (body <- sensor) as a (4, 4) rigid transform."""
    T = np.array(_numbers(data, "T_BS", 16, path, "16 numbers (4x4 row-major, body<-sensor)"))
    T = T.reshape(4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1]) or not is_rotation(T[:3, :3], tol=1e-4):
        raise DatasetError(
            f"{path}: T_BS: expected a rigid transform (rotation and translation, last row 0 0 0 1)"
        )
    return T


def read_camera_yaml(path: Path, frame_id: str) -> CameraModel:
    """A EuRoC camera `sensor.yaml` -> unrectified CameraModel (R = I, P = [K | 0])."""
    data = read_yaml_mapping(path, "a EuRoC camera sensor.yaml", DatasetError)
    model = data.get("camera_model", "pinhole")
    if model != "pinhole":
        raise DatasetError(f"{path}: camera_model: expected 'pinhole', got {model!r}")
    T_body_cam = read_T_BS(data, path)
    w, h = _numbers(data, "resolution", 2, path, "[width, height] in pixels")
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise DatasetError(
            f"{path}: resolution: expected two positive integers, got [{w:g}, {h:g}]"
        )
    fu, fv, cu, cv = _numbers(data, "intrinsics", 4, path, "[fu, fv, cu, cv]")
    dist = data.get("distortion_model")
    if dist not in _DISTORTION:
        raise DatasetError(
            f"{path}: distortion_model: expected one of {', '.join(_DISTORTION)}, got {dist!r}"
        )
    coeffs = _numbers(
        data, "distortion_coefficients", 4, path, "4 numbers (k1, k2, p1, p2 or k1..k4)"
    )
    D = np.array([*coeffs, 0.0] if dist == "radial-tangential" else coeffs)
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return CameraModel(
        width=int(w),
        height=int(h),
        K=K,
        D=D,
        distortion_model=_DISTORTION[dist],
        R_rect=np.eye(3),
        P=np.hstack([K, np.zeros((3, 1))]),
        T_body_cam=T_body_cam,
        frame_id=frame_id,
        source=f"euroc {path.parent.name}/sensor.yaml",
    )


def read_image_csv(path: Path, data_dir: Path) -> tuple[I64, list[Path]]:
    """`camN/data.csv` (timestamp [ns], filename) -> (stamps_ns, image paths)."""
    text = read_text(path, "a EuRoC image list (timestamp [ns], filename per line)", DatasetError)
    stamps: list[int] = []
    files: list[Path] = []
    lines: list[int] = []
    for k, (no, line) in enumerate(data_lines(text)):
        fields = [f.strip() for f in line.split(",")]
        if k == 0 and not fields[0].isdigit():
            continue  # header row without '#'
        if len(fields) != 2 or not fields[0].isdigit() or not fields[1]:
            raise DatasetError(
                f"{path}: line {no}: expected 'timestamp [ns],filename', got {line[:60]!r}"
            )
        stamps.append(int(fields[0]))
        files.append(data_dir / fields[1])
        lines.append(no)
    check_stamps_increasing(path, stamps, lines, DatasetError)
    if not stamps:
        raise DatasetError(f"{path}: no image rows, expected 'timestamp [ns],filename' lines")
    return np.asarray(stamps, dtype=np.int64), files


def pair_by_stamp(
    left: tuple[I64, list[Path]], right: tuple[I64, list[Path]], mav0_dir: Path
) -> tuple[StereoFiles, list[str]]:
    """Left/right images with equal stamps; each paired file must exist."""
    right_of = {int(s): p for s, p in zip(right[0], right[1], strict=True)}
    stamps: list[int] = []
    lefts: list[Path] = []
    rights: list[Path] = []
    for s, lp in zip(left[0], left[1], strict=True):
        rp = right_of.get(int(s))
        if rp is not None:
            stamps.append(int(s))
            lefts.append(require_file(lp, f"the cam0 image listed in {mav0_dir}/cam0/data.csv"))
            rights.append(require_file(rp, f"the cam1 image listed in {mav0_dir}/cam1/data.csv"))
    if not stamps:
        raise DatasetError(
            f"{mav0_dir}/cam1/data.csv: no timestamp equals one of "
            "cam0/data.csv, expected synchronised stereo images"
        )
    notes = []
    n_left, n_right = len(left[0]) - len(stamps), len(right[0]) - len(stamps)
    if n_left or n_right:
        notes.append(
            f"{n_left} cam0 and {n_right} cam1 images have no partner with the same "
            "timestamp and were left out"
        )
    return StereoFiles(np.asarray(stamps, dtype=np.int64), tuple(lefts), tuple(rights)), notes


# --------------------------------------------------------------------------- IMU


def read_imu(imu_dir: Path) -> tuple[ImuTable | None, dict[str, Any], list[str]]:
    """`imu0/` -> samples in the body frame, noise parameters, notes. Per-sample variances
    are density^2 * rate_hz (continuous-time white noise sampled at rate_hz)."""
    if not imu_dir.exists():
        return None, {}, ["no imu0/ folder: no IMU samples written"]
    require_dir(imu_dir, "the EuRoC IMU folder imu0/")
    stamps, values = read_stamped_csv(
        imu_dir / "data.csv", 6, "EuRoC IMU samples (timestamp [ns], w xyz [rad/s], a xyz [m/s^2])"
    )
    notes: list[str] = []
    gyro, accel = values[:, :3], values[:, 3:6]
    meta: dict[str, Any] = {"frame": "body"}
    yaml_path = imu_dir / "sensor.yaml"
    data: dict[str, Any] = {}
    if yaml_path.exists():
        data = read_yaml_mapping(yaml_path, "a EuRoC IMU sensor.yaml", DatasetError)
        T_BS = read_T_BS(data, yaml_path) if "T_BS" in data else np.eye(4)
        if not np.allclose(T_BS[:3, :3], np.eye(3), atol=1e-9):
            gyro, accel = gyro @ T_BS[:3, :3].T, accel @ T_BS[:3, :3].T
            notes.append(
                f"{yaml_path}: T_BS is not identity; IMU samples rotated into the "
                "body frame (lever arm ignored)"
            )
    else:
        notes.append(f"{yaml_path}: not found; IMU noise unknown (covariances written as 0)")
    rate_hz = _positive(data, "rate_hz", yaml_path)
    if rate_hz is None:
        dt = np.median(np.diff(stamps)) if len(stamps) > 1 else 0
        rate_hz = 1e9 / float(dt) if dt > 0 else 0.0
    meta["rate_hz"] = rate_hz
    for key in (
        "gyroscope_noise_density",
        "gyroscope_random_walk",
        "accelerometer_noise_density",
        "accelerometer_random_walk",
    ):
        v = _positive(data, key, yaml_path)
        if v is not None:
            meta[key] = v
    g_nd, a_nd = meta.get("gyroscope_noise_density"), meta.get("accelerometer_noise_density")
    gyro_var = g_nd**2 * rate_hz if g_nd is not None else 0.0
    accel_var = a_nd**2 * rate_hz if a_nd is not None else 0.0
    meta["gyro_var_rad2_s2"], meta["accel_var_m2_s4"] = gyro_var, accel_var
    return (
        ImuTable(
            stamps, np.ascontiguousarray(gyro), np.ascontiguousarray(accel), gyro_var, accel_var
        ),
        meta,
        notes,
    )


def _positive(data: dict[str, Any], key: str, path: Path) -> float | None:
    if key not in data:
        return None
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
        raise DatasetError(f"{path}: {key}: expected a number >= 0, got {v!r}")
    return float(v)


# --------------------------------------------------------------------------- ground truth


def read_ground_truth(gt_dir: Path) -> tuple[PoseTable | None, str]:
    """Ground truth in NED (`T_nav_body`), and the file it came from. `data.csv` (ns
    stamps, exact) is preferred over `groundtruth.tum`."""
    csv_path, tum_path = gt_dir / "data.csv", gt_dir / "groundtruth.tum"
    if csv_path.exists():
        stamps, values = read_stamped_csv(
            csv_path, 7, "EuRoC ground truth (timestamp [ns], p_RS_R xyz [m], q_RS wxyz, ...)"
        )
        q_wxyz = values[:, 3:7]
        norms = np.linalg.norm(q_wxyz, axis=1)
        bad = first_non_unit(norms)
        if bad is not None:
            raise DatasetError(
                f"{csv_path}: row {bad + 1}: quaternion q_RS (columns 5-8, "
                f"w x y z) has norm {norms[bad]:.4f}, expected 1"
            )
        p_world_m, q_world_body_xyzw = values[:, :3], q_wxyz[:, [1, 2, 3, 0]] / norms[:, None]
        source = str(csv_path)
    elif tum_path.exists():
        # a TUM file in the Vicon world frame: the table's nav-named columns hold world
        # coordinates until `world_to_ned` below
        world = read_tum(tum_path, DatasetError)
        if not len(world):
            raise DatasetError(f"{tum_path}: no poses, expected t x y z qx qy qz qw per line")
        stamps, p_world_m = world.stamps_ns, world.p_nav_m
        norms = np.linalg.norm(world.q_nav_body_xyzw, axis=1)
        q_world_body_xyzw = world.q_nav_body_xyzw / norms[:, None]
        source = str(tum_path)
    else:
        return None, ""
    return world_to_ned(stamps, p_world_m, q_world_body_xyzw), source


def world_to_ned(stamps_ns: I64, p_world_m: F64, q_world_body_xyzw: F64) -> PoseTable:
    """T_world_body (EuRoC Vicon world, z up) -> T_nav_body (NED), see `R_NED_WORLD`."""
    p_nav_m = p_world_m @ R_NED_WORLD.T
    C_nav_body = R_NED_WORLD @ quat_xyzw_to_matrix(q_world_body_xyzw)
    return PoseTable(stamps_ns, p_nav_m, matrix_to_quat_xyzw(C_nav_body))
