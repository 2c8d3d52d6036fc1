"""Small synthetic inputs for tests: ROS 2 logs written with cvslam's own LogWriter, and
feature sets of random values."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cvslam_cli.geometry.camera import CameraModel, translation_T
from cvslam_cli.geometry.rotations import make_T
from cvslam_cli.io.mcap_writer import LogWriter, camera_info_fields, header, raw_fields
from cvslam_cli.records.features import (
    DESCRIPTOR_SIZE,
    FeatureSet,
    FeatureSetBuilder,
    RigCalibration,
)

R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


@dataclass
class SynthLog:
    """What was written, to compare against what is read back."""

    path: Path
    left: list[tuple[int, np.ndarray]] = field(default_factory=list)
    right: list[tuple[int, np.ndarray]] = field(default_factory=list)
    imu: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)
    gt: list[tuple[int, np.ndarray]] = field(default_factory=list)


def camera(
    width: int = 64,
    height: int = 48,
    fx: float = 50.0,
    *,
    right: bool = False,
    baseline_m: float = 0.1,
    frame_id: str = "",
) -> CameraModel:
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
    P = np.hstack([K, np.array([[-fx * baseline_m if right else 0.0], [0.0], [0.0]])])
    T_body_left = make_T(R_BODY_CAM, np.zeros(3))
    T = T_body_left @ translation_T(baseline_m) if right else T_body_left
    return CameraModel(
        width=width,
        height=height,
        K=K,
        D=np.zeros(5),
        distortion_model="plumb_bob",
        P=P,
        T_body_cam=T,
        frame_id=frame_id,
    )


def write_stereo_log(
    path: Path,
    *,
    vehicle: str = "uav1",
    n_frames: int = 10,
    rate_hz: float = 20.0,
    size: tuple[int, int] = (64, 48),
    imu_rate_hz: float = 200.0,
    camera_info: bool = True,
    tf: bool = True,
    baseline_m: float = 0.1,
    right_offset_ns: int = 0,
    drop_right: tuple[int, ...] = (),
    nan_imu: tuple[int, ...] = (),
    backwards_imu_at: int | None = None,
    info_size: tuple[int, int] | None = None,
    fx: float = 50.0,
    t0_ns: int = 1_000_000_000,
    seed: int = 0,
    chunk_size: int = 1024 * 1024,
) -> SynthLog:
    rng = np.random.default_rng(seed)
    out = SynthLog(path)
    w, h = size
    iw, ih = info_size or size
    lf, rf = f"{vehicle}/left_camera_optical", f"{vehicle}/right_camera_optical"
    left_cam = camera(iw, ih, fx, frame_id=lf, baseline_m=baseline_m)
    right_cam = camera(iw, ih, fx, right=True, frame_id=rf, baseline_m=baseline_m)
    frame_dt = int(1e9 / rate_hz)
    imu_dt = int(1e9 / imu_rate_hz)
    duration = n_frames * frame_dt
    events: list[tuple[int, int, str, int]] = []  # (stamp, order, kind, index)
    for i in range(n_frames):
        events.append((t0_ns + i * frame_dt, 1, "left", i))
        if i not in drop_right:
            events.append((t0_ns + i * frame_dt + right_offset_ns, 2, "right", i))
        events.append((t0_ns + i * frame_dt, 3, "gt", i))
    for j in range(duration // imu_dt):
        events.append((t0_ns + j * imu_dt, 0, "imu", j))
    events.sort()
    with LogWriter(path, chunk_size=chunk_size) as log:
        if tf:
            log.write_tf_static(
                "/tf_static",
                t0_ns,
                [
                    (f"{vehicle}/base_link", lf, left_cam.T_body_cam),
                    (f"{vehicle}/base_link", rf, right_cam.T_body_cam),
                ],
            )
        for stamp, _, kind, idx in events:
            if kind in ("left", "right"):
                img = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
                cam = left_cam if kind == "left" else right_cam
                log.write_image(f"/{vehicle}/stereo/{kind}/image_raw", stamp, img, cam.frame_id)
                if camera_info:
                    log.write_camera_info(f"/{vehicle}/stereo/{kind}/camera_info", stamp, cam)
                getattr(out, kind).append((stamp, img))
            elif kind == "imu":
                gyro = rng.normal(0, 0.01, 3)
                acc = rng.normal(0, 0.1, 3) + np.array([0, 0, -9.81])
                if idx in nan_imu:
                    gyro[1] = np.nan
                s = stamp
                if backwards_imu_at is not None and idx == backwards_imu_at:
                    s = stamp - 5 * imu_dt
                log.write_imu(
                    f"/{vehicle}/imu", s, gyro, acc, f"{vehicle}/base_link", log_time_ns=stamp
                )
                if idx not in nan_imu:
                    out.imu.append((s, gyro, acc))
            else:
                p = np.array([0.1 * idx, 0.0, -10.0])
                log.write_pose(f"/{vehicle}/ground_truth/pose", stamp, p, [0, 0, 0, 1], "nav")
                out.gt.append((stamp, p))
    return out


# -- feature sets --------------------------------------------------------------------------


def feature_rig() -> RigCalibration:
    K = np.array([[450.0, 0, 376], [0, 450, 240], [0, 0, 1]])
    T = np.stack([np.eye(4), np.eye(4)])
    T[1, 0, 3] = 0.5
    return RigCalibration(
        K=np.stack([K, K]),
        D=np.zeros((2, 5)),
        distortion_model="plumb_bob",
        T_body_cam=T,
        size_px=np.array([[752, 480], [752, 480]]),
    )


def _feature_side(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    return {
        "uv_raw_px": rng.uniform(0, 700, (n, 2)),
        "uv_px": rng.uniform(0, 700, (n, 2)),
        "size_px": rng.uniform(1, 9, n),
        "angle_deg": rng.uniform(0, 360, n),
        "response": rng.uniform(0, 1, n),
        "octave": rng.integers(0, 4, n),
        "desc": rng.integers(0, 256, (n, DESCRIPTOR_SIZE)),
    }


def _feature_matches(rng: np.random.Generator, m: int, nl: int, nr: int) -> dict[str, np.ndarray]:
    return {
        "left": rng.integers(0, nl, m),
        "right": rng.integers(0, nr, m),
        "disparity_px": rng.uniform(0, 30, m),
        "distance": rng.uniform(0, 300, m),
        "ratio": rng.uniform(0, 0.8, m),
        "p_cam_m": rng.normal(size=(m, 3)),
        "cov_cam_m2": np.tile(np.eye(3), (m, 1, 1)),
        "landmark_id": rng.integers(-2, 50, m),
    }


def feature_set(seed: int = 0) -> FeatureSet:
    """Three frames of uav1 (5/6/3, 0/0/0 and 7/4/4 left/right keypoints and matches) with
    random values of the right shapes and dtypes."""
    rng = np.random.default_rng(seed)
    b = FeatureSetBuilder("uav1", feature_rig())
    for i, (nl, nr, m) in enumerate([(5, 6, 3), (0, 0, 0), (7, 4, 4)]):
        b.add_frame(
            1000 + i,
            _feature_side(rng, nl),
            _feature_side(rng, nr),
            _feature_matches(rng, m, max(nl, 1), max(nr, 1)),
        )
    return b.build()


def write_image_log(
    path: Path,
    stamps_ns: list[int],
    *,
    sizes: list[tuple[int, int]] | None = None,
    vehicle: str = "uav1",
    seed: int = 0,
    repeat_content: bool = True,
) -> Path:
    """A stereo log with one left/right pair (and CameraInfo) per entry of `stamps_ns`,
    recorded in that order at 20 Hz from log time 1 s (so header stamps may repeat, go
    backwards or be absurd); a repeated stamp repeats its images (a duplicated message) when
    `repeat_content`; `sizes`: (width, height) per pair (default 64x48; the CameraInfo stays
    64x48)."""
    rng = np.random.default_rng(seed)
    lf, rf = f"{vehicle}/left_camera_optical", f"{vehicle}/right_camera_optical"
    left_cam, right_cam = camera(frame_id=lf), camera(right=True, frame_id=rf)
    seen: dict[tuple[int, str], np.ndarray] = {}
    with LogWriter(path) as log:
        log.write_tf_static(
            "/tf_static",
            max(0, min(stamps_ns)),
            [
                (f"{vehicle}/base_link", lf, left_cam.T_body_cam),
                (f"{vehicle}/base_link", rf, right_cam.T_body_cam),
            ],
        )
        for i, stamp in enumerate(stamps_ns):
            w, h = sizes[i] if sizes else (64, 48)
            log_time = 10**9 + i * 50_000_000  # recorded in order, 20 Hz, whatever the stamps
            for side, cam in (("left", left_cam), ("right", right_cam)):
                img = rng.integers(0, 256, size=(h, w), dtype=np.uint8)
                if repeat_content:
                    img = seen.setdefault((stamp, side), img)
                fields = {"header": header(stamp, cam.frame_id), **raw_fields(img)}
                topic = f"/{vehicle}/stereo/{side}"
                log.write(f"{topic}/image_raw", "sensor_msgs/msg/Image", fields, stamp, log_time)
                info = camera_info_fields(cam, stamp)
                log.write(
                    f"{topic}/camera_info", "sensor_msgs/msg/CameraInfo", info, stamp, log_time
                )
    return path
