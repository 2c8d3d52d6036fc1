"""Shared pieces of the dataset importers: checked file reading and the log writer loop.

An importer first reads and checks the whole dataset description (calibration, timestamp
tables, file lists) into an `ImportPlan`, so that bad input is reported before any output
exists; `write_plan` then streams the images one at a time into the MCAP log.

Conventions of the written log (DESIGN.md sections 3 and 4), with `<v>` the vehicle:
- nav frame "nav" is NED; ground truth is `T_nav_body` as geometry_msgs/PoseStamped on
  `/<v>/ground_truth/pose` (frame_id "nav");
- `/tf_static` holds one TFMessage at the first stamp: `<v>/base_link` -> `<v>/left_camera_optical`
  and `<v>/right_camera_optical` (`T_body_cam`, camera optical frame x right, y down, z forward);
- images (mono8, lossless) and one CameraInfo per image (same stamp) use the optical frame ids;
  IMU samples use `<v>/base_link`;
- times are integer nanoseconds (`stamp_ns`); text seconds are converted exactly (no float).
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from cvslam_cli import __version__
from cvslam_cli.errors import CvslamError, DatasetError
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.output_frames import DatasetFrame
from cvslam_cli.geometry.rotations import matrix_to_quat_xyzw, nearest_rotation
from cvslam_cli.io.dataset_frames import dataset_frame_fields
from cvslam_cli.io.mcap_writer import LogWriter
from cvslam_cli.io.names import NAV_FRAME_ID, TF_STATIC_TOPIC, VehicleNames, vehicle_names
from cvslam_cli.io.textfiles import (
    check_stamps_increasing,
    data_lines,
    finite_floats,
    read_text,
)
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.poses import PoseTable


@dataclass(frozen=True)
class ImportSummary:
    """What an import wrote. `baseline_m`: distance between the optical centres;
    `duration_s`: first to last stereo pair; `notes`: things worth telling the user
    (unpaired images, the ground-truth file used, conversions applied)."""

    out_path: Path
    vehicle: str
    stereo_pairs: int
    imu_samples: int
    ground_truth_poses: int
    baseline_m: float
    duration_s: float
    notes: tuple[str, ...] = ()


def check_vehicle_name(vehicle: str) -> VehicleNames:
    return vehicle_names(vehicle, DatasetError)


# --------------------------------------------------------------------------- tables


@dataclass(frozen=True, eq=False)
class StereoFiles:
    """Image pairs to write: `stamps_ns` (N,) strictly increasing, one left and one right
    image file per stamp."""

    stamps_ns: I64
    left_paths: tuple[Path, ...]
    right_paths: tuple[Path, ...]

    def __len__(self) -> int:
        return len(self.left_paths)


@dataclass(frozen=True, eq=False)
class ImuTable:
    """IMU samples in the body frame: `stamps_ns` (N,) increasing, `gyro_rad_s` (N, 3),
    `accel_m_s2` (N, 3); `gyro_var`, `accel_var`: per-sample variances (0 = unknown)."""

    stamps_ns: I64
    gyro_rad_s: F64
    accel_m_s2: F64
    gyro_var: float = 0.0
    accel_var: float = 0.0

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True, eq=False)
class ImportPlan:
    """Everything checked and ready to write; `rig` cameras carry their frame ids and
    `T_body_cam`; `ground_truth` is in the nav frame (NED)."""

    names: VehicleNames
    rig: StereoRig
    frames: StereoFiles
    imu: ImuTable | None
    ground_truth: PoseTable | None
    metadata: dict[str, dict[str, str]]
    notes: tuple[str, ...] = field(default_factory=tuple)


# --------------------------------------------------------------------------- files


def require_dir(path: Path, what: str) -> Path:
    if not path.exists():
        raise DatasetError(f"{path}: not found, expected {what}")
    if not path.is_dir():
        raise DatasetError(f"{path}: is not a folder, expected {what}")
    return path


def require_file(path: Path, what: str) -> Path:
    if not path.exists():
        raise DatasetError(f"{path}: not found, expected {what}")
    if not path.is_file():
        raise DatasetError(f"{path}: is not a file, expected {what}")
    return path


def read_stamped_csv(path: Path, n_values: int, what: str) -> tuple[I64, F64]:
    """EuRoC-style CSV: integer ns timestamp, then at least `n_values` numbers per row
    (extra columns ignored); '#' lines and a non-numeric first header line are skipped.
    Returns (stamps_ns (N,), values (N, n_values)), stamps strictly increasing."""
    text = read_text(path, what, DatasetError)
    stamps: list[int] = []
    values: list[list[float]] = []
    lines: list[int] = []
    for k, (no, line) in enumerate(data_lines(text)):
        fields = [f.strip() for f in line.split(",")]
        if k == 0 and not _is_number(fields[0]):
            continue  # a header row without '#'
        if len(fields) < 1 + n_values:
            raise DatasetError(
                f"{path}: line {no}: expected a timestamp and {n_values} "
                f"comma-separated numbers, got {len(fields)} fields"
            )
        try:
            stamps.append(int(fields[0]))
            values.append(finite_floats(fields[1 : 1 + n_values]))
        except ValueError:
            raise DatasetError(
                f"{path}: line {no}: expected an integer timestamp [ns] and "
                f"{n_values} finite numbers, got {line[:60]!r}"
            ) from None
        lines.append(no)
    if not stamps:
        raise DatasetError(f"{path}: no data rows, expected {what}")
    check_stamps_increasing(path, stamps, lines, DatasetError)
    return np.asarray(stamps, dtype=np.int64), np.asarray(values, dtype=float)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_mono8(path: Path) -> tuple[np.ndarray, bool]:
    """An 8-bit image file as (H, W) uint8; returns (image, was_colour)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        if not path.is_file():
            raise DatasetError(f"{path}: image not found")
        raise DatasetError(f"{path}: cannot decode image, expected an 8-bit PNG")
    if img.dtype != np.uint8:
        raise DatasetError(f"{path}: image has {img.dtype} pixels, expected 8-bit grey")
    if img.ndim == 2:
        return img, False
    if img.ndim == 3 and img.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(img, code), True
    raise DatasetError(f"{path}: image of shape {img.shape}, expected (H, W) grey")


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file (decodes it once)."""
    img, _ = read_mono8(path)
    return int(img.shape[1]), int(img.shape[0])


def check_rig(rig: StereoRig, source: str) -> None:
    """`StereoRig.validate` with its error re-raised as a DatasetError naming `source`."""
    try:
        rig.validate(source)
    except CvslamError as exc:
        raise DatasetError(str(exc)) from None


def camera_json(cam: CameraModel) -> str:
    """Calibration of one camera as a JSON string (for the "cvslam.rig" metadata record)."""
    return json.dumps(
        {
            "frame_id": cam.frame_id,
            "source": cam.source,
            "width": cam.width,
            "height": cam.height,
            "K": np.asarray(cam.K).tolist(),
            "D": [float(d) for d in cam.D],
            "distortion_model": cam.distortion_model,
            "R_rect": np.asarray(cam.R_rect).tolist(),
            "P": None if cam.P is None else np.asarray(cam.P).tolist(),
            "T_body_cam": np.asarray(cam.T_body_cam).tolist(),
        }
    )


def import_metadata(
    dataset: str,
    source_dir: Path,
    vehicle: str,
    conversion: str,
    body_frame: str,
    ground_truth: Path | None,
    dataset_frame: DatasetFrame | None = None,
    **extra: str,
) -> dict[str, str]:
    """The "cvslam.import" metadata record: where the log came from and how its frames
    were converted to NED, in words (`conversion`) and, with `dataset_frame`, as numbers
    (`io/dataset_frames.py`, for `cvslam export --frame dataset`); `extra` entries come
    before the cvslam version."""
    return {
        "dataset": dataset,
        "source_dir": str(source_dir.resolve()),
        "vehicle": vehicle,
        "nav_frame": "NED",
        "conversion": conversion,
        "body_frame": body_frame,
        "ground_truth": "none" if ground_truth is None else str(ground_truth.resolve()),
        **(dataset_frame_fields(dataset_frame) if dataset_frame is not None else {}),
        **extra,
        "cvslam_version": __version__,
    }


def rig_metadata(names: VehicleNames, rig: StereoRig, **extra: str) -> dict[str, str]:
    return {
        "vehicle": names.vehicle,
        "body_frame": names.body_frame,
        "left": camera_json(rig.left),
        "right": camera_json(rig.right),
        "baseline_m": json.dumps(rig.baseline_m),
        "rectified": json.dumps(rig.rectified),
        **extra,
    }


# --------------------------------------------------------------------------- writing

_FRAME, _IMU, _GT = 0, 1, 2  # write order of messages sharing a stamp


def _events(plan: ImportPlan) -> Iterator[tuple[int, int, int]]:
    """(stamp_ns, kind, index) of every message to write, in stamp order."""
    streams: list[Iterator[tuple[int, int, int]]] = [
        ((int(s), _FRAME, i) for i, s in enumerate(plan.frames.stamps_ns))
    ]
    if plan.imu is not None:
        streams.append((int(s), _IMU, i) for i, s in enumerate(plan.imu.stamps_ns))
    if plan.ground_truth is not None:
        streams.append((int(s), _GT, i) for i, s in enumerate(plan.ground_truth.stamps_ns))
    return heapq.merge(*streams)


def write_plan(
    plan: ImportPlan, out_path: Path, *, progress: bool = False, desc: str = "import"
) -> ImportSummary:
    """Write the log: images are read and written one pair at a time. On any error the
    partial output is removed (LogWriter) and the error propagates."""
    names, rig, frames = plan.names, plan.rig, plan.frames
    firsts = [int(frames.stamps_ns[0])]
    if plan.imu is not None:
        firsts.append(int(plan.imu.stamps_ns[0]))
    if plan.ground_truth is not None:
        firsts.append(int(plan.ground_truth.stamps_ns[0]))
    t0_ns = min(firsts)
    colour = False
    out_path = Path(out_path)
    bar = tqdm(
        total=len(frames), desc=desc, unit="pair", disable=None if progress else True, leave=False
    )
    try:
        with LogWriter(out_path) as log:
            log.write_tf_static(
                TF_STATIC_TOPIC,
                t0_ns,
                [
                    (names.body_frame, names.left_frame, rig.left.T_body_cam),
                    (names.body_frame, names.right_frame, rig.right.T_body_cam),
                ],
            )
            for stamp_ns, kind, i in _events(plan):
                if kind == _FRAME:
                    for path, cam, img_topic, info_topic in (
                        (
                            frames.left_paths[i],
                            rig.left,
                            names.topics.left_image,
                            names.topics.left_info,
                        ),
                        (
                            frames.right_paths[i],
                            rig.right,
                            names.topics.right_image,
                            names.topics.right_info,
                        ),
                    ):
                        img, was_colour = read_mono8(path)
                        colour |= was_colour
                        h, w = img.shape
                        if (w, h) != (cam.width, cam.height):
                            raise DatasetError(
                                f"{path}: image is {w}x{h}, expected "
                                f"{cam.width}x{cam.height} ({cam.source})"
                            )
                        log.write_camera_info(info_topic, stamp_ns, cam)
                        log.write_image(img_topic, stamp_ns, img, cam.frame_id)
                    bar.update(1)
                elif kind == _IMU:
                    imu = plan.imu
                    assert imu is not None
                    log.write_imu(
                        names.topics.imu,
                        stamp_ns,
                        imu.gyro_rad_s[i],
                        imu.accel_m_s2[i],
                        names.body_frame,
                        gyro_var=imu.gyro_var,
                        accel_var=imu.accel_var,
                    )
                else:
                    gt = plan.ground_truth
                    assert gt is not None
                    log.write_pose(
                        names.topics.ground_truth,
                        stamp_ns,
                        gt.p_nav_m[i],
                        gt.q_nav_body_xyzw[i],
                        NAV_FRAME_ID,
                    )
            notes = list(plan.notes)
            if colour:
                notes.append("colour images were converted to grey (mono8)")
            for name, data in plan.metadata.items():
                if name == "cvslam.import":
                    data = {**data, "notes": json.dumps(notes)}
                log.add_metadata(name, data)
    finally:
        bar.close()
    return ImportSummary(
        out_path=out_path,
        vehicle=names.vehicle,
        stereo_pairs=len(frames),
        imu_samples=0 if plan.imu is None else len(plan.imu),
        ground_truth_poses=0 if plan.ground_truth is None else len(plan.ground_truth),
        baseline_m=rig.baseline_m,
        duration_s=float(frames.stamps_ns[-1] - frames.stamps_ns[0]) * 1e-9,
        notes=tuple(notes),
    )


def pose_table_from_T(stamps_ns: I64, T_nav_body: F64) -> PoseTable:
    """PoseTable from (N, 4, 4) transforms (rotations re-orthonormalised)."""
    R = np.stack([nearest_rotation(T[:3, :3]) for T in T_nav_body])
    return PoseTable(
        np.asarray(stamps_ns, dtype=np.int64), T_nav_body[:, :3, 3].copy(), matrix_to_quat_xyzw(R)
    )
