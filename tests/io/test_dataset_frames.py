"""The dataset frame the importers record (`cvslam.import` metadata): undoing it on the
imported ground truth gives back the dataset's own poses, for KITTI (camera 0 in the
poses.txt world, also when the first pose is not the identity) and EuRoC (IMU body in the
Vicon world)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.output_frames import reexpress
from cvslam_cli.geometry.rotations import make_T, quat_xyzw_to_matrix
from cvslam_cli.io.dataset_frames import (
    IMPORT_RECORD,
    dataset_frame_of,
    log_dataset_frames,
)
from cvslam_cli.io.importers.euroc import plan_euroc
from cvslam_cli.io.importers.kitti import import_kitti, plan_kitti, read_poses
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.records.poses import PoseTable
from tests.io.test_importers import real_dir


def as_T(table: PoseTable) -> np.ndarray:
    R = quat_xyzw_to_matrix(table.q_nav_body_xyzw)
    return np.stack([make_T(r, p) for r, p in zip(R, table.p_nav_m, strict=True)])


def undo(plan) -> PoseTable:
    """The plan's ground truth (nav, body) in the dataset frame its metadata records."""
    frame = dataset_frame_of(plan.metadata[IMPORT_RECORD], "plan")
    assert frame is not None
    return reexpress(plan.ground_truth, frame.T_world_nav, frame.T_body_sensor)


def kitti_folder(root: Path, T_world_cam0: np.ndarray) -> Path:
    """A 3-frame KITTI folder of small grey images with the given poses."""
    rng = np.random.default_rng(0)
    for side in ("image_0", "image_1"):
        (root / side).mkdir(parents=True)
        for i in range(len(T_world_cam0)):
            cv2.imwrite(str(root / side / f"{i:06d}.png"), rng.integers(0, 255, (32, 64), np.uint8))
    P0 = [[50.0, 0, 32, 0], [0, 50.0, 16, 0], [0, 0, 1, 0]]
    P1 = [[50.0, 0, 32, -25.0], [0, 50.0, 16, 0], [0, 0, 1, 0]]
    (root / "calib.txt").write_text(
        "".join(
            f"P{k}: " + " ".join(repr(float(v)) for v in np.ravel(P)) + "\n"
            for k, P in enumerate((P0, P1))
        )
    )
    (root / "poses.txt").write_text(
        "".join(" ".join(repr(float(v)) for v in T[:3].ravel()) + "\n" for T in T_world_cam0)
    )
    return root


def test_kitti_clip_a_ground_truth_back_in_its_own_frame():
    seq = real_dir("kitti_clip_a")
    plan = plan_kitti(seq, "car")
    record = plan.metadata[IMPORT_RECORD]
    assert "camera 0" in record["dataset_sensor_frame"]
    poses = read_poses(seq / "poses.txt", len(plan.ground_truth))
    np.testing.assert_allclose(as_T(undo(plan)), poses, atol=2e-6)  # poses.txt: 7 digits


def test_kitti_first_pose_not_identity_is_kept(tmp_path):
    rng = np.random.default_rng(3)
    Ts = []
    for _ in range(3):
        q = rng.normal(size=4)
        Ts.append(make_T(quat_xyzw_to_matrix(q / np.linalg.norm(q)), rng.normal(size=3)))
    seq = kitti_folder(tmp_path / "seq", np.stack(Ts))
    plan = plan_kitti(seq, "car")
    np.testing.assert_allclose(plan.ground_truth.p_nav_m[0], 0.0, atol=1e-12)  # nav: re-anchored
    np.testing.assert_allclose(as_T(undo(plan)), np.stack(Ts), atol=1e-12)  # world: as given
    # and through a written log
    log = tmp_path / "car.mcap"
    import_kitti(seq, log, "car")
    ((path, (vehicle, frame)),) = log_dataset_frames([log]).items()
    assert vehicle == "car" and path == log and frame is not None
    np.testing.assert_allclose(
        frame.T_world_nav @ frame.T_body_sensor, Ts[0], atol=1e-12
    )  # the body at the first frame is the nav origin


def test_euroc_micro_ground_truth_back_in_the_vicon_world():
    mav0 = real_dir("euroc_v101_micro", "mav0")
    plan = plan_euroc(mav0, "uav1")
    world = read_tum(mav0 / "state_groundtruth_estimate0" / "groundtruth.tum")
    back = undo(plan)
    np.testing.assert_array_equal(back.stamps_ns, world.stamps_ns)
    np.testing.assert_allclose(as_T(back), as_T(world), atol=1e-12)
    assert (
        "IMU" in plan.metadata[IMPORT_RECORD]["dataset_sensor_frame"]
        or "imu0" in (plan.metadata[IMPORT_RECORD]["dataset_sensor_frame"])
    )


def test_records_without_or_with_a_broken_frame():
    assert dataset_frame_of({"dataset": "kitti"}, "x.mcap") is None
    with pytest.raises(CvslamError, match=r"^x\.mcap: metadata cvslam\.import: unusable dataset"):
        dataset_frame_of({"T_nav_world": "[[1, 0]]", "T_body_sensor": "[]"}, "x.mcap")


def test_simulated_logs_have_no_dataset_frame(small_image_run):
    assert log_dataset_frames(sorted(small_image_run.glob("*.mcap"))) == {}
