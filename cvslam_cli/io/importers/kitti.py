"""KITTI odometry sequence folder -> cvslam MCAP log.

Layout read (`seq_dir/`): rectified grey images in `image_l/` + `image_r/` or `image_0/` +
`image_1/` (PNG, paired in name order); `calib.txt` with the projection matrices P0 (left)
and P1 (right), 12 numbers each, either labelled (`P0: ...`, `P1: ...`; other labelled lines
ignored) or unlabelled (first line P0, second line P1); optional `times.txt` (seconds per
frame, else frames are 1/rate_hz apart from t = 0); optional `poses.txt` (12 numbers per
frame: row-major 3x4 T_world_cam0, world = the first cam0 frame).

Frames: body frame FRD with its origin at cam0's optical centre: body x = camera forward
(optical z), body y = camera right (optical x), body z = camera down (optical y), so
`T_body_cam0` has rotation `R_BODY_CAM` and no translation, and `T_body_cam1` =
`T_body_cam0 @ translation(b, 0, 0)` with b = (P0[0,3] - P1[0,3]) / P1[0,0].
The nav frame (NED) is the body frame at the first pose ("north" = the initial forward
direction, not geographic north): T_nav_body = T_body_cam0 T_world_cam0(0)^-1 T_world_cam0
T_body_cam0^-1, so the first ground-truth pose is the identity.
Cameras are rectified: K = P[:, :3], D = zeros ("plumb_bob"), R = I, P as in calib.txt.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from cvslam_cli.errors import DatasetError
from cvslam_cli.geometry.camera import CameraModel, StereoRig, translation_T
from cvslam_cli.geometry.output_frames import DatasetFrame
from cvslam_cli.geometry.rotations import invert_T, is_rotation, make_T, nearest_rotation
from cvslam_cli.io.importers.common import (
    ImportPlan,
    ImportSummary,
    StereoFiles,
    check_rig,
    check_vehicle_name,
    image_size,
    import_metadata,
    pose_table_from_T,
    require_dir,
    rig_metadata,
    write_plan,
)
from cvslam_cli.io.textfiles import (
    check_stamps_increasing,
    data_lines,
    read_text,
    seconds_text_to_ns,
)
from cvslam_cli.records.arrays import F64, I64

#: Camera optical frame (x right, y down, z forward) -> body FRD (x forward, y right, z down).
R_BODY_CAM: F64 = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
T_BODY_CAM0: F64 = make_T(R_BODY_CAM, np.zeros(3))

CONVERSION = (
    "KITTI poses T_world_cam0 (world = first cam0 optical frame, x right, y down, z forward) "
    "were converted to T_nav_body = T_body_cam0 T_world_cam0(0)^-1 T_world_cam0 T_body_cam0^-1 "
    "with R_body_cam0 = [[0,0,1],[1,0,0],[0,1,0]]: the nav frame (NED) is the body frame at "
    "the first frame (north = initial forward direction, east = initial right, down = initial "
    "camera down), so the first pose is the identity. The body frame (<vehicle>/base_link) is "
    "FRD (x forward = optical z, y right = optical x, z down = optical y) with its origin at "
    "cam0's optical centre."
)

_LABEL = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*:\s*(.*)$")
_IMAGE_DIRS = (("image_l", "image_r"), ("image_0", "image_1"))


def import_kitti(
    seq_dir: Path, out_path: Path, vehicle: str, *, rate_hz: float = 10.0, progress: bool = False
) -> ImportSummary:
    """Import a KITTI odometry sequence folder into the MCAP log `out_path` for vehicle
    `vehicle` (frames `1 / rate_hz` apart when there is no times.txt). Raises
    `DatasetError` naming the file for any bad input; on error no output file is left."""
    plan = plan_kitti(Path(seq_dir), vehicle, rate_hz=rate_hz)
    return write_plan(plan, Path(out_path), progress=progress, desc=f"kitti {vehicle}")


def plan_kitti(seq_dir: Path, vehicle: str, *, rate_hz: float = 10.0) -> ImportPlan:
    """Read and check everything but the pixels of all images after the first."""
    names = check_vehicle_name(vehicle)
    require_dir(
        seq_dir, "a KITTI sequence folder (image_l/ + image_r/ or image_0/ + image_1/, calib.txt)"
    )
    notes: list[str] = []
    left_dir, right_dir = _image_dirs(seq_dir)
    lefts, rights = sorted(left_dir.glob("*.png")), sorted(right_dir.glob("*.png"))
    if not lefts:
        raise DatasetError(f"{left_dir}: no .png images")
    if len(lefts) != len(rights):
        raise DatasetError(
            f"{right_dir}: {len(rights)} images, expected {len(lefts)} like "
            f"{left_dir.name}/ (left and right must pair one to one)"
        )
    if [p.name for p in lefts] != [p.name for p in rights]:
        notes.append(
            f"{left_dir.name}/ and {right_dir.name}/ file names differ; paired in name order"
        )
    n = len(lefts)

    calib_path = seq_dir / "calib.txt"
    P0, P1 = read_calib(calib_path)
    width, height = image_size(lefts[0])
    rig = rig_from_projections(
        P0, P1, width, height, names.left_frame, names.right_frame, calib_path
    )
    check_rig(rig, str(calib_path))

    times_path = seq_dir / "times.txt"
    if times_path.exists():
        stamps_ns = read_times(times_path, n)
        notes.append("timestamps from times.txt")
    else:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise DatasetError(
                f"{seq_dir}: no times.txt and frame rate {rate_hz!r} Hz is not positive"
            )
        stamps_ns = np.array([round(i * 1e9 / rate_hz) for i in range(n)], dtype=np.int64)
        notes.append(f"no times.txt: frames {1.0 / rate_hz:g} s apart from t = 0")
    frames = StereoFiles(stamps_ns, tuple(lefts), tuple(rights))

    poses_path = seq_dir / "poses.txt"
    gt = None
    T_world_cam0_first = np.eye(4)  # KITTI's world: the first camera-0 frame
    if poses_path.exists():
        T_world_cam0 = read_poses(poses_path, n)
        T_world_cam0_first = T_world_cam0[0]
        T_nav_body, reanchored = poses_to_nav(T_world_cam0)
        gt = pose_table_from_T(stamps_ns, T_nav_body)
        notes.append("ground truth from poses.txt")
        if reanchored:
            notes.append(
                "poses.txt: first pose is not the identity; poses re-expressed "
                "relative to the first frame"
            )
    else:
        notes.append("no poses.txt: no ground truth")

    metadata = {
        "cvslam.import": import_metadata(
            "kitti",
            seq_dir,
            vehicle,
            CONVERSION,
            "FRD at cam0 (x forward, y right, z down)",
            poses_path if gt is not None else None,
            dataset_frame(T_world_cam0_first),
            timestamps=(
                str(times_path.resolve()) if times_path.exists() else f"{rate_hz:g} Hz from t = 0"
            ),
        ),
        "cvslam.rig": rig_metadata(
            names, rig, P0=json.dumps(P0.tolist()), P1=json.dumps(P1.tolist())
        ),
    }
    return ImportPlan(names, rig, frames, None, gt, metadata, tuple(notes))


def dataset_frame(T_world_cam0_first: F64) -> DatasetFrame:
    """KITTI's own frame: poses of camera 0 (`T_BODY_CAM0`) in the world of poses.txt, the
    nav frame being the body at the first frame (`poses_to_nav`):
    T_nav_world = T_body_cam0 T_world_cam0(0)^-1."""
    T_first = make_T(nearest_rotation(T_world_cam0_first[:3, :3]), T_world_cam0_first[:3, 3])
    return DatasetFrame(
        T_BODY_CAM0 @ invert_T(T_first),
        T_BODY_CAM0,
        "KITTI world (poses.txt: the first camera-0 optical frame, x right, y down, z forward)",
        "camera 0 (left camera optical frame)",
    )


def _image_dirs(seq_dir: Path) -> tuple[Path, Path]:
    for left, right in _IMAGE_DIRS:
        if (seq_dir / left).is_dir() or (seq_dir / right).is_dir():
            return (
                require_dir(seq_dir / left, f"left images ({left}/ next to {right}/)"),
                require_dir(seq_dir / right, f"right images ({right}/ next to {left}/)"),
            )
    raise DatasetError(
        f"{seq_dir}: no image folders, expected image_l/ and image_r/ (or image_0/ and image_1/)"
    )


# --------------------------------------------------------------------------- calibration


def _twelve(path: Path, no: int, text: str, what: str) -> F64:
    fields = text.split()
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise DatasetError(
            f"{path}: line {no}: expected 12 numbers ({what}), got {text[:60]!r}"
        ) from None
    if len(values) != 12 or not np.all(np.isfinite(values)):
        raise DatasetError(
            f"{path}: line {no}: expected 12 finite numbers ({what}), got {len(values)}"
        )
    return np.array(values).reshape(3, 4)


def read_calib(path: Path) -> tuple[F64, F64]:
    """`calib.txt` -> (P0, P1), each (3, 4). Labelled (`P0: ...`) or unlabelled lines."""
    text = read_text(path, "KITTI calibration (P0 and P1, 12 numbers each)", DatasetError)
    lines = list(data_lines(text))
    labelled = {}
    for no, line in lines:
        m = _LABEL.match(line)
        if m:
            labelled[m.group(1)] = (no, m.group(2))
    if labelled:
        out = []
        for key in ("P0", "P1"):
            if key not in labelled:
                raise DatasetError(
                    f"{path}: no line '{key}:', expected labelled P0 and P1 lines of 12 numbers"
                )
            no, rest = labelled[key]
            out.append(_twelve(path, no, rest, f"{key}, row-major 3x4"))
        return out[0], out[1]
    if len(lines) < 2:
        raise DatasetError(
            f"{path}: {len(lines)} line(s), expected two lines P0 and P1 of 12 numbers each"
        )
    return (
        _twelve(path, lines[0][0], lines[0][1], "P0, row-major 3x4"),
        _twelve(path, lines[1][0], lines[1][1], "P1, row-major 3x4"),
    )


def rig_from_projections(
    P0: F64, P1: F64, width: int, height: int, left_frame: str, right_frame: str, calib_path: Path
) -> StereoRig:
    """Rectified stereo rig from the KITTI projection matrices; see the module docstring."""
    if P1[0, 0] <= 0:
        raise DatasetError(
            f"{calib_path}: P1[0,0] = {P1[0, 0]:g}, expected a positive focal length"
        )
    b_m = float((P0[0, 3] - P1[0, 3]) / P1[0, 0])
    if not b_m > 0:
        raise DatasetError(
            f"{calib_path}: P1[0,3] = {P1[0, 3]:g} gives a baseline of {b_m:g} m, "
            "expected the right camera to the right of the left (P1[0,3] < 0)"
        )
    cams = []
    for P, frame_id, T_body_cam in (
        (P0, left_frame, T_BODY_CAM0),
        (P1, right_frame, T_BODY_CAM0 @ translation_T(b_m)),
    ):
        cams.append(
            CameraModel(
                width=width,
                height=height,
                K=P[:, :3].copy(),
                D=np.zeros(5),
                distortion_model="plumb_bob",
                R_rect=np.eye(3),
                P=P.copy(),
                T_body_cam=T_body_cam,
                frame_id=frame_id,
                source="kitti calib.txt",
            )
        )
    return StereoRig(cams[0], cams[1])


# --------------------------------------------------------------------------- times, poses


def read_times(path: Path, n_frames: int) -> I64:
    """`times.txt`: one time in seconds per frame -> (n_frames,) stamps_ns, increasing."""
    text = read_text(path, "KITTI frame times (seconds, one per line)", DatasetError)
    stamps: list[int] = []
    lines: list[int] = []
    for no, line in data_lines(text):
        try:
            stamps.append(seconds_text_to_ns(line))
        except ValueError:
            raise DatasetError(
                f"{path}: line {no}: expected a time in seconds, got {line[:60]!r}"
            ) from None
        lines.append(no)
    check_stamps_increasing(path, stamps, lines, DatasetError)
    if len(stamps) != n_frames:
        raise DatasetError(f"{path}: {len(stamps)} times, expected {n_frames} (one per frame)")
    return np.asarray(stamps, dtype=np.int64)


def read_poses(path: Path, n_frames: int) -> F64:
    """`poses.txt` -> (n_frames, 4, 4) T_world_cam0."""
    text = read_text(path, "KITTI poses (12 numbers per frame)", DatasetError)
    Ts = []
    for no, line in data_lines(text):
        T = np.eye(4)
        T[:3] = _twelve(path, no, line, "row-major 3x4 T_world_cam0")
        if not is_rotation(T[:3, :3], tol=1e-3):
            raise DatasetError(
                f"{path}: line {no}: the 3x3 part is not a rotation, expected "
                "a row-major 3x4 rigid transform"
            )
        Ts.append(T)
    if len(Ts) != n_frames:
        raise DatasetError(f"{path}: {len(Ts)} poses, expected {n_frames} (one per frame)")
    return np.stack(Ts)


def poses_to_nav(T_world_cam0: F64) -> tuple[F64, bool]:
    """(N, 4, 4) T_world_cam0 -> (N, 4, 4) T_nav_body with nav = body at the first frame;
    also whether the first pose had to be re-anchored (was not the identity)."""
    T_first_world = invert_T(T_world_cam0[0])
    reanchored = not np.allclose(T_world_cam0[0], np.eye(4), atol=1e-6)
    T_cam_body = invert_T(T_BODY_CAM0)
    T_nav_body = np.stack([T_BODY_CAM0 @ T_first_world @ T @ T_cam_body for T in T_world_cam0])
    return T_nav_body, reanchored
