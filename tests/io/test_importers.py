"""Dataset importers: EuRoC and KITTI folders -> MCAP logs, read back through LogSet.

Real-data tests read `../shared/data` (or $CVSLAM_SHARED_DATA) and skip when it is absent;
the synthetic folders (round trips, bad input) are written to tmp_path.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cvslam_cli.config import load_config
from cvslam_cli.errors import DatasetError
from cvslam_cli.geometry.rotations import (
    make_T,
    matrix_to_euler_zyx,
    quat_xyzw_to_matrix,
)
from cvslam_cli.io.importers.common import ImportSummary
from cvslam_cli.io.importers.euroc import import_euroc
from cvslam_cli.io.importers.kitti import import_kitti
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.textfiles import seconds_text_to_ns as seconds_to_ns
from cvslam_cli.records.log import ImuSample, PoseRecord, StereoFrame

# --------------------------------------------------------------------------- helpers


@dataclass
class ReadBack:
    """An imported log read back (frames kept as stamps, plus the first pair's images)."""

    logs: LogSet
    source: McapLogSource
    vehicle: str
    frame_stamps_ns: list[int]
    first_frame: StereoFrame
    imu: list[ImuSample]
    gt: list[PoseRecord]


def read_back(path: Path) -> ReadBack:
    source = McapLogSource(path)
    logs = LogSet([source], load_config().logs)
    (vehicle,) = logs.vehicles
    stamps: list[int] = []
    first: StereoFrame | None = None
    imu: list[ImuSample] = []
    gt: list[PoseRecord] = []
    for rec in logs.records():
        if isinstance(rec, StereoFrame):
            stamps.append(rec.stamp_ns)
            first = first or rec
        elif isinstance(rec, ImuSample):
            imu.append(rec)
        elif isinstance(rec, PoseRecord):
            gt.append(rec)
    assert first is not None
    return ReadBack(logs, source, vehicle, stamps, first, imu, gt)


REPO = Path(__file__).resolve().parents[2]


def real_dir(*parts: str) -> Path:
    """A folder of the real-data set (skips the test when absent)."""
    root = Path(os.environ.get("CVSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
    path = root.joinpath(*parts)
    if not path.is_dir():
        pytest.skip(f"real data folder {path} not found (set CVSLAM_SHARED_DATA)")
    return path


def data_rows(path: Path) -> list[str]:
    return [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def assert_nothing_written(out: Path) -> None:
    left = sorted(p.name for p in out.parent.iterdir()) if out.parent.exists() else []
    assert left == [], f"files left behind after a failed import: {left}"


# --------------------------------------------------------------------------- EuRoC (real)


@pytest.fixture(scope="module")
def euroc_import(tmp_path_factory: pytest.TempPathFactory) -> tuple[ImportSummary, ReadBack]:
    mav0 = real_dir("euroc_v101_micro", "mav0")
    out = tmp_path_factory.mktemp("euroc") / "v101.mcap"
    summary = import_euroc(mav0, out, "uav1")
    return summary, read_back(out)


def test_euroc_micro_counts_and_rates(euroc_import):
    summary, rb = euroc_import
    mav0 = real_dir("euroc_v101_micro", "mav0")
    n_imu_rows = len(data_rows(mav0 / "imu0" / "data.csv"))
    assert summary.stereo_pairs == 95 and rb.logs.stats["uav1"].stereo_pairs == 95
    assert len(rb.frame_stamps_ns) == 95
    assert summary.imu_samples == n_imu_rows == len(rb.imu)
    assert summary.ground_truth_poses == 95 == len(rb.gt)
    assert summary.duration_s == pytest.approx(4.7, abs=1e-6)
    imu_stats = rb.logs.stats["uav1"].topics["/uav1/imu"]
    assert imu_stats.rate_hz == pytest.approx(200.0, rel=1e-2)
    # cam1/data.csv lists 4 images past the end of cam0: reported, not paired
    assert any("4 cam1" in n for n in summary.notes)
    assert rb.imu[0].frame_id == "uav1/base_link"
    first_row = data_rows(mav0 / "imu0" / "data.csv")[0].split(",")
    assert rb.imu[0].stamp_ns == int(first_row[0])
    np.testing.assert_array_equal(rb.imu[0].gyro_rad_s, [float(v) for v in first_row[1:4]])
    np.testing.assert_array_equal(rb.imu[0].accel_m_s2, [float(v) for v in first_row[4:7]])


def test_euroc_micro_calibration(euroc_import):
    _, rb = euroc_import
    mav0 = real_dir("euroc_v101_micro", "mav0")
    rig = rb.logs.rig("uav1")
    assert rig.left.fx == pytest.approx(458.654)
    assert rig.left.D[0] == pytest.approx(-0.28340811)
    assert rig.left.distortion_model == "plumb_bob" and rig.left.D.shape == (5,)
    assert rig.right.cx == pytest.approx(379.999)
    assert rig.baseline_m == pytest.approx(0.110, abs=1e-3)
    assert not rig.rectified
    for cam, name in ((rig.left, "cam0"), (rig.right, "cam1")):
        text = (mav0 / name / "sensor.yaml").read_text().split("\n", 1)[1]  # drop %YAML:1.0
        T_BS = np.array(yaml.safe_load(text)["T_BS"]["data"]).reshape(4, 4)
        assert "/tf_static" in cam.source  # extrinsics came from /tf_static
        np.testing.assert_allclose(cam.T_body_cam, T_BS, atol=1e-9)
    # IMU covariance = noise density^2 * rate (ADIS16448 figures of imu0/sensor.yaml)
    raw = next(iter(rb.source.messages(["/uav1/imu"])))
    assert raw.msg.angular_velocity_covariance[0] == pytest.approx(1.6968e-4**2 * 200)
    assert raw.msg.linear_acceleration_covariance[8] == pytest.approx(2.0e-3**2 * 200)
    meta = rb.source.metadata()
    assert meta["cvslam.import"]["dataset"] == "euroc"
    assert meta["cvslam.import"]["nav_frame"] == "NED"
    assert "R_ned_world" in meta["cvslam.import"]["conversion"]
    assert json.loads(meta["cvslam.rig"]["left"])["K"][0][0] == pytest.approx(458.654)
    assert json.loads(meta["cvslam.rig"]["imu"])["gyroscope_noise_density"] == 1.6968e-4


def test_euroc_micro_images_identical_to_png(euroc_import):
    _, rb = euroc_import
    mav0 = real_dir("euroc_v101_micro", "mav0")
    first = data_rows(mav0 / "cam0" / "data.csv")[0].split(",")
    assert rb.first_frame.stamp_ns == int(first[0])
    for side, cam in (("left", "cam0"), ("right", "cam1")):
        png = cv2.imread(str(mav0 / cam / "data" / first[1]), cv2.IMREAD_GRAYSCALE)
        img = getattr(rb.first_frame, side)
        assert img.encoding == "mono8" and img.frame_id == f"uav1/{side}_camera_optical"
        np.testing.assert_array_equal(img.image, png)


def test_euroc_micro_ground_truth_in_ned(euroc_import):
    _, rb = euroc_import
    # groundtruth.tum row 1: 1403715273.26214 0.878895 2.183400 0.948427 (world x y z, z up)
    #                        q = -0.824237 -0.106942 -0.551702 0.069433 (x y z w)
    gt0 = rb.gt[0]
    assert gt0.frame_id == "nav"
    assert gt0.stamp_ns == 1_403_715_273_262_140_000
    # NED: north = world y, east = world x, down = -world z
    np.testing.assert_allclose(gt0.p_m, [2.183400, 0.878895, -0.948427], atol=1e-12)
    C_world_body = quat_xyzw_to_matrix(np.array([-0.824237, -0.106942, -0.551702, 0.069433]))
    expected = np.vstack([C_world_body[1], C_world_body[0], -C_world_body[2]])
    np.testing.assert_allclose(quat_xyzw_to_matrix(gt0.q_xyzw), expected, atol=1e-9)
    # the vehicle is nearly static: every position within 5 mm of the first
    p = np.array([g.p_m for g in rb.gt])
    assert np.abs(p - p[0]).max() < 5e-3


# --------------------------------------------------------------------------- KITTI (real)


@pytest.fixture(scope="module")
def kitti_a(tmp_path_factory: pytest.TempPathFactory) -> tuple[ImportSummary, ReadBack]:
    seq = real_dir("kitti_clip_a")
    out = tmp_path_factory.mktemp("kitti_a") / "a.mcap"
    return import_kitti(seq, out, "car"), read_back(out)


def _path_length_m(gt: list[PoseRecord]) -> float:
    p = np.array([g.p_m for g in gt])
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def test_kitti_clip_a(kitti_a):
    summary, rb = kitti_a
    seq = real_dir("kitti_clip_a")
    assert summary.stereo_pairs == 51 == len(rb.frame_stamps_ns)
    assert summary.imu_samples == 0 and not rb.imu
    assert rb.frame_stamps_ns == [i * 100_000_000 for i in range(51)]
    assert summary.duration_s == pytest.approx(5.0)
    rig = rb.logs.rig("car")
    P1 = np.loadtxt(seq / "calib.txt")[1].reshape(3, 4)
    assert rig.baseline_m == pytest.approx(0.537, abs=1e-3)
    assert rig.baseline_m == pytest.approx(-P1[0, 3] / P1[0, 0], rel=1e-9)
    assert summary.baseline_m == pytest.approx(rig.baseline_m)
    assert rig.rectified
    np.testing.assert_allclose(rig.right.P, P1)
    # ground truth: identity first, then ~59.9 m almost straight ahead (north)
    assert len(rb.gt) == 51
    np.testing.assert_allclose(rb.gt[0].p_m, 0.0, atol=1e-12)
    np.testing.assert_allclose(quat_xyzw_to_matrix(rb.gt[0].q_xyzw), np.eye(3), atol=1e-9)
    north, east, down = rb.gt[-1].p_m
    assert 58.5 < north < 61.0 and abs(east) < 2.0 and abs(down) < 2.0
    assert _path_length_m(rb.gt) == pytest.approx(59.9, abs=0.3)
    png = cv2.imread(str(seq / "image_l" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(rb.first_frame.left.image, png)
    assert rb.source.metadata()["cvslam.import"]["dataset"] == "kitti"


def test_kitti_clip_b(tmp_path):
    seq = real_dir("kitti_clip_b")
    summary = import_kitti(seq, tmp_path / "b.mcap", "car2")
    rb = read_back(tmp_path / "b.mcap")
    assert summary.stereo_pairs == 51 == len(rb.frame_stamps_ns)
    rig = rb.logs.rig("car2")
    assert rig.rectified and rig.baseline_m == pytest.approx(0.537, abs=1e-3)
    np.testing.assert_allclose(rb.gt[0].p_m, 0.0, atol=1e-12)
    assert _path_length_m(rb.gt) == pytest.approx(51.8, abs=0.3)
    yaw_deg = np.degrees(matrix_to_euler_zyx(quat_xyzw_to_matrix(rb.gt[-1].q_xyzw))[2])
    assert abs(yaw_deg) == pytest.approx(98.0, abs=3.0)  # the 98 degree turn, about down


# --------------------------------------------------------------------------- synthetic folders

SIZE = (40, 30)  # width, height
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _fmt(values) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(values, dtype=float).reshape(-1))


def make_kitti(
    root: Path,
    n: int = 3,
    *,
    dirs: tuple[str, str] = ("image_l", "image_r"),
    labelled: bool = False,
    times: list[str] | None = None,
    poses: np.ndarray | None = None,
    seed: int = 0,
) -> Path:
    """A KITTI-like folder; returns it. `poses`: (n, 4, 4) T_world_cam0."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    for d in dirs:
        (root / d).mkdir()
        for i in range(n):
            img = rng.integers(0, 256, size=(SIZE[1], SIZE[0]), dtype=np.uint8)
            cv2.imwrite(str(root / d / f"{i:06d}.png"), img)
    fx, b = 35.0, 0.5
    P0 = np.array([[fx, 0, 20.0, 0], [0, fx, 15.0, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -fx * b
    if labelled:
        calib = (
            "\n".join(
                [
                    f"P0: {_fmt(P0)}",
                    f"P1: {_fmt(P1)}",
                    f"P2: {_fmt(P0)}",
                    f"Tr: {_fmt(np.eye(4)[:3])}",
                ]
            )
            + "\n"
        )
    else:
        calib = f"{_fmt(P0)}\n{_fmt(P1)}"  # no trailing newline, like the shared clips
    (root / "calib.txt").write_text(calib)
    if times is not None:
        (root / "times.txt").write_text("\n".join(times) + "\n")
    if poses is not None:
        (root / "poses.txt").write_text("\n".join(_fmt(T[:3]) for T in poses) + "\n")
    return root


def _yaw_cam(theta: float) -> np.ndarray:
    """Rotation about the camera y axis (down): turning right by theta."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _kitti_motion(n: int, offset: np.ndarray | None = None) -> np.ndarray:
    """Camera 1 m forward per frame (optical z) turning right 0.1 rad per frame."""
    Ts = np.stack([make_T(_yaw_cam(0.1 * i), np.array([0.0, 0.0, float(i)])) for i in range(n)])
    return Ts if offset is None else np.stack([offset @ T for T in Ts])


@pytest.mark.parametrize("layout", ["unlabelled_image_lr_no_times", "labelled_image_01_times"])
def test_kitti_synthetic_round_trip(tmp_path, layout):
    n = 3
    labelled = layout.startswith("labelled")
    dirs = ("image_0", "image_1") if labelled else ("image_l", "image_r")
    times = ["0.000000e+00", "1.036594e-01", "2.073190e-01"] if labelled else None
    seq = make_kitti(
        tmp_path / "seq", n, dirs=dirs, labelled=labelled, times=times, poses=_kitti_motion(n)
    )
    out = tmp_path / "out" / "k.mcap"
    summary = import_kitti(seq, out, "ugv1", rate_hz=20.0)
    assert summary.stereo_pairs == n and summary.ground_truth_poses == n
    assert summary.out_path == out and out.exists()
    assert not out.with_name("k.mcap.partial").exists()
    rb = read_back(out)
    expected = [0, 103_659_400, 207_319_000] if labelled else [0, 50_000_000, 100_000_000]
    assert rb.frame_stamps_ns == expected
    assert [g.stamp_ns for g in rb.gt] == expected
    rng = np.random.default_rng(0)  # the images make_kitti wrote, in order
    written = {
        d: [rng.integers(0, 256, size=(SIZE[1], SIZE[0]), dtype=np.uint8) for _ in range(n)]
        for d in dirs
    }
    np.testing.assert_array_equal(rb.first_frame.left.image, written[dirs[0]][0])
    np.testing.assert_array_equal(rb.first_frame.right.image, written[dirs[1]][0])
    rig = rb.logs.rig("ugv1")
    assert rig.rectified and rig.baseline_m == pytest.approx(0.5)
    np.testing.assert_allclose(rig.left.T_body_cam[:3, :3], R_BODY_CAM, atol=1e-12)
    # 1 m forward per frame -> north; turning right 0.1 rad per frame -> yaw +0.1 (NED)
    for i, g in enumerate(rb.gt):
        C_nav_body = quat_xyzw_to_matrix(g.q_xyzw)
        np.testing.assert_allclose(matrix_to_euler_zyx(C_nav_body), [0, 0, 0.1 * i], atol=1e-9)
        np.testing.assert_allclose(g.p_m, [i, 0, 0], atol=1e-9)
    tf = rb.logs.static_transforms.lookup("ugv1/base_link", "ugv1/right_camera_optical")
    np.testing.assert_allclose(tf[:3, 3], [0, 0.5, 0], atol=1e-12)  # right cam 0.5 m right


def test_kitti_poses_not_starting_at_identity_are_reanchored(tmp_path):
    offset = make_T(_yaw_cam(0.7), np.array([3.0, -1.0, 2.0]))
    seq = make_kitti(tmp_path / "seq", 3, poses=_kitti_motion(3, offset))
    summary = import_kitti(seq, tmp_path / "k.mcap", "ugv1")
    assert any("re-expressed" in n for n in summary.notes)
    gt = read_back(tmp_path / "k.mcap").gt
    np.testing.assert_allclose([g.p_m for g in gt], [[0, 0, 0], [1, 0, 0], [2, 0, 0]], atol=1e-9)


def _cam_yaml(T_BS: np.ndarray, width: int = SIZE[0]) -> str:
    data = ", ".join(f"{v:.12g}" for v in T_BS.reshape(-1))
    return (
        "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\n"
        f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"
        f"rate_hz: 20\nresolution: [{width}, {SIZE[1]}]\ncamera_model: pinhole\n"
        "intrinsics: [35.0, 34.0, 20.5, 15.5] #fu, fv, cu, cv\n"
        "distortion_model: radial-tangential\n"
        "distortion_coefficients: [-0.28, 0.07, 0.0002, 1.8e-05]\n"
    )


IMU_YAML = """%YAML:1.0
sensor_type: imu
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 200
gyroscope_noise_density: 1.0e-03
gyroscope_random_walk: 1.0e-05
accelerometer_noise_density: 2.0e-02
accelerometer_random_walk: 3.0e-03
"""

EUROC_T0_NS = 1_403_715_273_262_142_976
R_BODY_EUROC_CAM = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def make_euroc(root: Path, n: int = 3, *, gt: str | None = "csv", seed: int = 0) -> Path:
    """A EuRoC-like mav0 folder (40x30 images, 200 Hz IMU); returns mav0."""
    rng = np.random.default_rng(seed)
    mav0 = root / "mav0"
    stamps = [EUROC_T0_NS + i * 50_000_000 for i in range(n)]
    for cam, y_m in (("cam0", -0.05), ("cam1", 0.05)):
        (mav0 / cam / "data").mkdir(parents=True)
        rows = ["#timestamp [ns],filename"]
        for s in stamps:
            img = rng.integers(0, 256, size=(SIZE[1], SIZE[0]), dtype=np.uint8)
            cv2.imwrite(str(mav0 / cam / "data" / f"{s}.png"), img)
            rows.append(f"{s},{s}.png")
        (mav0 / cam / "data.csv").write_text("\n".join(rows) + "\n")
        T_BS = make_T(R_BODY_EUROC_CAM, np.array([0.01, y_m, 0.0]))
        (mav0 / cam / "sensor.yaml").write_text(_cam_yaml(T_BS))
    (mav0 / "imu0").mkdir()
    imu_rows = ["#timestamp [ns],w_x,w_y,w_z,a_x,a_y,a_z"]
    for j in range(10 * (n - 1) + 1):
        w, a = rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3) + np.array([9.81, 0, 0])
        imu_rows.append(
            ",".join([str(EUROC_T0_NS + j * 5_000_000)] + [repr(float(v)) for v in (*w, *a)])
        )
    (mav0 / "imu0" / "data.csv").write_text("\n".join(imu_rows) + "\n")
    (mav0 / "imu0" / "sensor.yaml").write_text(IMU_YAML)
    gt_dir = mav0 / "state_groundtruth_estimate0"
    c45 = np.sqrt(0.5)  # q_RS: 90 degrees about world z (w x y z = c45 0 0 c45)
    if gt == "csv":
        gt_dir.mkdir()
        rows = [
            "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
            "q_RS_y [], q_RS_z [], v_x, v_y, v_z, bw_x, bw_y, bw_z, ba_x, ba_y, ba_z"
        ]
        rows += [f"{s},1.0,2.0,{3.0 + i},{c45},0,0,{c45}" + ",0" * 9 for i, s in enumerate(stamps)]
        (gt_dir / "data.csv").write_text("\n".join(rows) + "\n")
    elif gt == "tum":
        gt_dir.mkdir()
        rows = ["# timestamp(s) tx ty tz qx qy qz qw"]
        rows += [
            f"{1403715273.26214 + 0.05 * i:.5f} 1.0 2.0 {3.0 + i} 0 0 {c45} {c45}" for i in range(n)
        ]
        (gt_dir / "groundtruth.tum").write_text("\n".join(rows) + "\n")
    return mav0


@pytest.mark.parametrize("gt", ["csv", "tum", None])
def test_euroc_synthetic_round_trip(tmp_path, gt):
    mav0 = make_euroc(tmp_path / "ds", 3, gt=gt)
    out = tmp_path / "out" / "e.mcap"
    summary = import_euroc(mav0.parent, out, "uav2")  # the folder holding mav0/ also works
    rb = read_back(out)
    stamps = [EUROC_T0_NS + i * 50_000_000 for i in range(3)]
    assert rb.frame_stamps_ns == stamps and summary.stereo_pairs == 3
    assert summary.imu_samples == 21 == len(rb.imu)
    rows = data_rows(mav0 / "imu0" / "data.csv")
    for s, row in zip(rb.imu, rows, strict=True):
        vals = row.split(",")
        assert s.stamp_ns == int(vals[0])
        np.testing.assert_array_equal(
            np.r_[s.gyro_rad_s, s.accel_m_s2], [float(v) for v in vals[1:]]
        )
    raw = next(iter(rb.source.messages(["/uav2/imu"])))
    assert raw.msg.angular_velocity_covariance[4] == pytest.approx(1e-3**2 * 200)
    png = cv2.imread(str(mav0 / "cam1" / "data" / f"{stamps[0]}.png"), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(rb.first_frame.right.image, png)
    rig = rb.logs.rig("uav2")
    assert rig.baseline_m == pytest.approx(0.1)
    np.testing.assert_allclose(rig.T_left_right[:3, 3], [0.1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rig.left.D, [-0.28, 0.07, 0.0002, 1.8e-05, 0.0])
    np.testing.assert_allclose(rig.left.P, np.hstack([rig.left.K, np.zeros((3, 1))]))
    if gt is None:
        assert not rb.gt and summary.ground_truth_poses == 0
        return
    assert len(rb.gt) == 3
    gt_stamps = (
        stamps
        if gt == "csv"
        else [seconds_to_ns(f"{1403715273.26214 + 0.05 * i:.5f}") for i in range(3)]
    )
    assert [g.stamp_ns for g in rb.gt] == gt_stamps
    if gt == "tum":
        assert gt_stamps[0] == 1_403_715_273_262_140_000  # exact, no float rounding
    # world (1, 2, 3 + i), z up -> NED (north = y, east = x, down = -z)
    np.testing.assert_allclose(
        [g.p_m for g in rb.gt], [[2, 1, -3 - i] for i in range(3)], atol=1e-12
    )
    # body x along world y (north), body y along -world x (west), body z up
    C_nav_body = quat_xyzw_to_matrix(rb.gt[0].q_xyzw)
    np.testing.assert_allclose(C_nav_body, np.diag([1.0, -1.0, -1.0]), atol=1e-12)


# --------------------------------------------------------------------------- bad input

Mutation = Callable[[Path], None]


def _append_line(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text + "\n")


def _write(path: Path, text: str | bytes) -> None:
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)


def _first_png(d: Path) -> Path:
    return sorted(d.glob("*.png"))[0]


def _last_png(d: Path) -> Path:
    return sorted(d.glob("*.png"))[-1]


KITTI_BAD: dict[str, tuple[Mutation, str]] = {
    "missing calib.txt": (lambda s: (s / "calib.txt").unlink(), "calib.txt"),
    "calib line with 11 numbers": (
        lambda s: _write(
            s / "calib.txt",
            "\n".join(
                [
                    (s / "calib.txt").read_text().splitlines()[0],
                    " ".join((s / "calib.txt").read_text().splitlines()[1].split()[:11]),
                ]
            ),
        ),
        "calib.txt: line 2: expected 12 finite numbers",
    ),
    "calib with one line": (
        lambda s: _write(s / "calib.txt", (s / "calib.txt").read_text().splitlines()[0]),
        "calib.txt: 1 line(s)",
    ),
    "calib not numbers": (lambda s: _write(s / "calib.txt", "a b c\nd e f\n"), "calib.txt"),
    "right camera on the left": (
        lambda s: _write(s / "calib.txt", (s / "calib.txt").read_text().replace("-1.75", "1.75")),
        "calib.txt: P1[0,3]",
    ),
    "left/right count mismatch": (lambda s: _last_png(s / "image_r").unlink(), "image_r"),
    "no image folders": (lambda s: (s / "image_l").rename(s / "left"), "image_l"),
    "poses count mismatch": (
        lambda s: _write(
            s / "poses.txt", "\n".join((s / "poses.txt").read_text().splitlines()[:2])
        ),
        "poses.txt: 2 poses, expected 3",
    ),
    "pose not a rotation": (
        lambda s: _append_line(s / "poses.txt", _fmt(np.ones((3, 4)))),
        "poses.txt: line 4",
    ),
    "times count mismatch": (
        lambda s: _write(s / "times.txt", "0.0\n0.1\n"),
        "times.txt: 2 times, expected 3",
    ),
    "times not increasing": (
        lambda s: _write(s / "times.txt", "0.0\n0.2\n0.1\n"),
        "times.txt: line 3",
    ),
    "corrupt PNG": (lambda s: _write(_last_png(s / "image_r"), b"not a png"), "000002.png"),
    "image size changes": (
        lambda s: cv2.imwrite(str(_last_png(s / "image_l")), np.zeros((30, 41), np.uint8)),
        "000002.png: image is 41x30, expected 40x30",
    ),
}


@pytest.mark.parametrize("case", list(KITTI_BAD))
def test_kitti_bad_input_raises_dataset_error(tmp_path, case):
    mutate, expected = KITTI_BAD[case]
    seq = make_kitti(tmp_path / "seq", 3, times=["0", "0.1", "0.2"], poses=_kitti_motion(3))
    mutate(seq)
    out = tmp_path / "out" / "k.mcap"
    with pytest.raises(DatasetError) as err:
        import_kitti(seq, out, "ugv1")
    msg = str(err.value)
    assert expected in msg and "\n" not in msg
    assert str(seq) in msg  # names the folder or file at fault
    assert_nothing_written(out)


EUROC_BAD: dict[str, tuple[Mutation, str]] = {
    "missing cam1/sensor.yaml": (
        lambda m: (m / "cam1" / "sensor.yaml").unlink(),
        "cam1/sensor.yaml: not found",
    ),
    "missing cam0 folder": (lambda m: (m / "cam0").rename(m / "camX"), "cam0: not found"),
    "malformed yaml": (
        lambda m: _write(m / "cam0" / "sensor.yaml", "%YAML:1.0\nT_BS: [1, 2\n"),
        "cam0/sensor.yaml: not valid YAML at line",
    ),
    "T_BS with 15 numbers": (
        lambda m: _write(
            m / "cam1" / "sensor.yaml", _cam_yaml(np.eye(4)).replace("data: [1, 0,", "data: [0,")
        ),
        "cam1/sensor.yaml: T_BS: expected 16 numbers",
    ),
    "unknown distortion model": (
        lambda m: _write(
            m / "cam0" / "sensor.yaml",
            _cam_yaml(np.eye(4)).replace("radial-tangential", "fisheye624"),
        ),
        "cam0/sensor.yaml: distortion_model",
    ),
    "bad cam csv row": (
        lambda m: _append_line(m / "cam0" / "data.csv", "12x,a.png"),
        "cam0/data.csv: line 5",
    ),
    "bad imu row": (
        lambda m: _append_line(m / "imu0" / "data.csv", "1,2,3"),
        "imu0/data.csv: line 23",
    ),
    "imu stamps go back": (
        lambda m: _append_line(m / "imu0" / "data.csv", "5" + ",0" * 6),
        "imu0/data.csv: line 23: timestamp 0.000000005 s does not increase",
    ),
    "bad ground truth quaternion": (
        lambda m: _append_line(
            m / "state_groundtruth_estimate0" / "data.csv", f"{EUROC_T0_NS + 10**9},0,0,0,2,0,0,0"
        ),
        "state_groundtruth_estimate0/data.csv: row 4",
    ),
    "no common stamps": (
        lambda m: _write(m / "cam1" / "data.csv", "#t,f\n1,1.png\n"),
        "cam1/data.csv",
    ),
    "listed image missing": (
        lambda m: _first_png(m / "cam0" / "data").unlink(),
        f"cam0/data/{EUROC_T0_NS}.png: not found",
    ),
    "corrupt PNG": (
        lambda m: _write(_last_png(m / "cam1" / "data"), b"\x89PNG broken"),
        f"cam1/data/{EUROC_T0_NS + 100_000_000}.png: cannot decode",
    ),
    "image size differs from resolution": (
        lambda m: _write(m / "cam0" / "sensor.yaml", _cam_yaml(np.eye(4), width=44)),
        f"cam0/data/{EUROC_T0_NS}.png: image is 40x30, expected 44x30",
    ),
}


@pytest.mark.parametrize("case", list(EUROC_BAD))
def test_euroc_bad_input_raises_dataset_error(tmp_path, case):
    mutate, expected = EUROC_BAD[case]
    mav0 = make_euroc(tmp_path / "ds", 3)
    mutate(mav0)
    out = tmp_path / "out" / "e.mcap"
    with pytest.raises(DatasetError) as err:
        import_euroc(mav0, out, "uav1")
    msg = str(err.value)
    assert expected in msg and "\n" not in msg
    assert str(mav0) in msg
    assert_nothing_written(out)


def test_missing_folders_and_bad_vehicle_name(tmp_path):
    out = tmp_path / "out" / "x.mcap"
    with pytest.raises(DatasetError, match="nope: not found"):
        import_euroc(tmp_path / "nope", out, "uav1")
    with pytest.raises(DatasetError, match="nope: not found"):
        import_kitti(tmp_path / "nope", out, "ugv1")
    seq = make_kitti(tmp_path / "seq", 2)
    with pytest.raises(DatasetError, match="vehicle name"):
        import_kitti(seq, out, "ugv 1")
    with pytest.raises(DatasetError, match="frame rate"):
        import_kitti(seq, out, "ugv1", rate_hz=0.0)
    assert_nothing_written(out)


def test_failed_import_keeps_no_partial_but_leaves_other_files(tmp_path):
    """A failure while writing removes the .partial and never replaces an existing log."""
    seq = make_kitti(tmp_path / "seq", 3)
    out = tmp_path / "out" / "k.mcap"
    import_kitti(seq, out, "ugv1")
    before = out.read_bytes()
    _write(_last_png(seq / "image_l"), b"garbage")
    with pytest.raises(DatasetError, match=r"000002\.png"):
        import_kitti(seq, out, "ugv1")
    assert sorted(p.name for p in out.parent.iterdir()) == ["k.mcap"]
    assert out.read_bytes() == before


def test_seconds_to_ns_is_exact():
    assert seconds_to_ns("1403715273.26214") == 1_403_715_273_262_140_000
    assert seconds_to_ns("1.036594e-01") == 103_659_400
    assert seconds_to_ns("0.0000000005") == 0  # half to even
    assert seconds_to_ns("0.0000000015") == 2
    with pytest.raises(ValueError):
        seconds_to_ns("nan")
