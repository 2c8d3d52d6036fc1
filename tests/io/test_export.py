"""`cvslam export`: the estimates in nav, ENU or the dataset's own frame, as TUM, KITTI or
EuRoC files; on KITTI clip a, evo's APE and RPE of the export against KITTI's own poses.txt
equal `cvslam eval`'s (the test of issue 19)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cvslam_cli.io.run_layout import RunLayout
from cvslam_cli.io.trajectory import read_euroc_csv, read_kitti, read_tum, write_tum
from cvslam_cli.records.poses import PoseTable
from tests.io.test_dataset_frames import as_T

REPO = Path(__file__).resolve().parents[2]


def random_table(n: int, seed: int) -> PoseTable:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, 3:])  # w >= 0, as written back
    stamps = 10**18 + np.arange(n, dtype=np.int64) * 50_000_000
    return PoseTable(stamps, rng.normal(scale=50.0, size=(n, 3)), q)


@pytest.fixture
def fused(tmp_path) -> tuple[Path, dict[str, PoseTable]]:
    """A run directory with only the fuse trajectories of two vehicles (and a dead
    reckoning, which is not exported)."""
    run = tmp_path / "run"
    tables = {"uav1": random_table(30, 1), "ugv1": random_table(12, 2)}
    fuse = RunLayout(run).fuse()
    for v, t in tables.items():
        write_tum(fuse.trajectory(v), t)
        write_tum(fuse.trajectory(v, deadreckoning=True), random_table(3, 3))
    return run, {v: read_tum(fuse.trajectory(v)) for v in tables}  # as written (9 decimals)


def test_nav_in_each_format_reads_back(fused, cvslam):
    run, tables = fused
    for fmt in ("tum", "kitti", "euroc"):
        r = cvslam("export", run, "--format", fmt)
        assert r.code == 0, r.err
    out = RunLayout(run).export_dir("fuse", "nav")
    assert out == run / "export" / "fuse_nav"
    assert sorted(p.name for p in out.iterdir()) == [
        "uav1.csv", "uav1.tum", "uav1.txt", "uav1_times.txt",
        "ugv1.csv", "ugv1.tum", "ugv1.txt", "ugv1_times.txt",
    ]  # fmt: skip
    for v, t in tables.items():
        tum = read_tum(out / f"{v}.tum")
        np.testing.assert_array_equal(tum.stamps_ns, t.stamps_ns)
        np.testing.assert_allclose(as_T(tum), as_T(t), atol=2e-9)
        csv = read_euroc_csv(out / f"{v}.csv")
        np.testing.assert_array_equal(csv.stamps_ns, t.stamps_ns)
        np.testing.assert_allclose(as_T(csv), as_T(t), atol=1e-12)
        stamps = read_tum_times(out / f"{v}_times.txt")
        kitti = read_kitti(out / f"{v}.txt", stamps)
        np.testing.assert_array_equal(kitti.stamps_ns, t.stamps_ns)
        np.testing.assert_allclose(as_T(kitti), as_T(t), atol=1e-12)


def read_tum_times(path: Path) -> np.ndarray:
    from cvslam_cli.io.textfiles import seconds_text_to_ns

    return np.array([seconds_text_to_ns(x) for x in path.read_text().split()], dtype=np.int64)


def test_enu_is_z_up_with_the_body_unchanged(fused, cvslam, tmp_path):
    run, tables = fused
    out = tmp_path / "mine"
    r = cvslam("export", run, "--frame", "enu", "-o", out)
    assert r.code == 0, r.err
    for v, t in tables.items():
        enu = read_tum(out / f"{v}.tum")
        n, e, d = t.p_nav_m.T
        np.testing.assert_allclose(enu.p_nav_m, np.stack([e, n, -d], axis=1), atol=2e-9)
        R_enu_nav = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
        np.testing.assert_allclose(as_T(enu)[:, :3, :3], R_enu_nav @ as_T(t)[:, :3, :3], atol=2e-8)
    assert "in ENU" in (out / "uav1.tum").read_text().splitlines()[0]


def test_unknown_source_names_the_fuse_folders(fused, cvslam):
    run, _ = fused
    r = cvslam("export", run, "--source", "fuse_ekf")
    assert r.code == 1 and r.err.count("\n") == 1
    assert f"{run}: no estimates in fuse_ekf/ (fuse folders: fuse)" in r.err


def test_dataset_frame_of_a_simulation_is_one_clear_line(small_image_run, tmp_path, cvslam):
    run = tmp_path / "run"
    shutil.copytree(small_image_run, run)
    r = cvslam("export", run, "--frame", "dataset")
    assert r.code == 1 and r.err.count("\n") == 1 and "Traceback" not in r.err
    assert f"{run}: --frame dataset: vehicle uav1: its logs (" in r.err
    assert "uav1.mcap" in r.err and "record no dataset frame" in r.err
    assert not (run / "export").exists()


# -- KITTI clip a: evo on the export against KITTI's own poses.txt ---------------------------


@pytest.fixture(scope="module")
def kitti_a(shared_data, tmp_path_factory) -> tuple[Path, Path]:
    """KITTI clip a imported, extracted, fused (configs/kitti.yaml) and evaluated."""
    from cvslam_cli.cli import main

    clip = shared_data / "kitti_clip_a"
    if not clip.is_dir():
        pytest.skip(f"{clip} not found")
    run = tmp_path_factory.mktemp("kitti_a")
    log = run / "car.mcap"
    steps = [
        ["-q", "import", "kitti", clip, "--vehicle", "car", "-o", log],
        ["-q", "extract", log, "-o", run],
        ["-q", "fuse", run, "--config", REPO / "configs" / "kitti.yaml"],
        ["-q", "eval", run],
        ["-q", "export", run, "--frame", "dataset", "--format", "kitti"],
        ["-q", "export", run, "--frame", "dataset", "--format", "tum"],
    ]
    for args in steps:
        with pytest.raises(SystemExit) as exc:
            main([str(a) for a in args])
        assert exc.value.code in (0, None), args
    return clip, run


def _eval_row(run: Path) -> dict:
    rows = pd.read_csv(RunLayout(run).eval.metrics_csv)
    (row,) = rows[(rows["run"] == "fuse") & (rows["vehicle"] == "car")].to_dict("records")
    return row


def test_evo_rpe_and_ape_of_the_kitti_export_equal_eval(kitti_a):
    from evo.core import metrics
    from evo.tools import file_interface

    clip, run = kitti_a
    ref = file_interface.read_kitti_poses_file(str(clip / "poses.txt"))
    est = file_interface.read_kitti_poses_file(str(run / "export" / "fuse_dataset" / "car.txt"))
    assert est.num_poses == ref.num_poses == 51
    # KITTI: first = I, the run's initial pose; with a window the trajectory holds its
    # estimate given the frames after it (docs/fuse_outputs.md, "Trajectories"), within the
    # initial pose's prior (attitude 5 mrad, position 0.1 m: here 3.6 mrad, under 1 um)
    np.testing.assert_allclose(est.poses_se3[0], np.eye(4), atol=0.015)
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, 1.0, metrics.Unit.frames)
    rpe.process_data((ref, est))
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    row = _eval_row(run)
    # poses.txt has 7 significant digits: evo uses them as written, eval the imported truth
    assert rpe.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(
        row["rpe_frame_rmse_m"], rel=1e-5
    )
    assert ape.get_statistic(metrics.StatisticsType.rmse) == pytest.approx(
        row["ate_rmse_m"], rel=1e-5
    )
    # the nav-frame trajectory, read against poses.txt as is, is what the issue found wrong
    nav = file_interface.read_tum_trajectory_file(str(run / "fuse" / "car.tum"))
    wrong = metrics.RPE(metrics.PoseRelation.translation_part, 1.0, metrics.Unit.frames)
    wrong.process_data((ref, type(ref)(poses_se3=nav.poses_se3)))
    assert wrong.get_statistic(metrics.StatisticsType.rmse) > 5 * row["rpe_frame_rmse_m"]


def test_kitti_tum_export_is_the_same_poses_with_stamps(kitti_a):
    _, run = kitti_a
    out = run / "export" / "fuse_dataset"
    tum = read_tum(out / "car.tum")
    kitti = read_kitti(out / "car.txt", read_tum_times(out / "car_times.txt"))
    np.testing.assert_array_equal(tum.stamps_ns, kitti.stamps_ns)
    np.testing.assert_allclose(as_T(tum), as_T(kitti), atol=1e-8)
    np.testing.assert_array_equal(tum.stamps_ns, read_tum(run / "fuse" / "car.tum").stamps_ns)


def test_euroc_dataset_frame_through_evo(shared_data, tmp_path, cvslam):
    """EuRoC micro imported; an estimate equal to the log's ground truth (nav frame) exported
    in the dataset frame (IMU in the Vicon world) reads with evo's EuRoC reader and matches
    the dataset's own ground truth to rounding."""
    from evo.core import metrics, sync
    from evo.tools import file_interface

    from cvslam_cli.config import load_config
    from cvslam_cli.io.logs import ground_truth_tables, open_logs

    mav0 = shared_data / "euroc_v101_micro" / "mav0"
    if not mav0.is_dir():
        pytest.skip(f"{mav0} not found")
    run, log = tmp_path / "run", tmp_path / "uav1.mcap"
    assert cvslam("-q", "import", "euroc", mav0, "--vehicle", "uav1", "-o", log).code == 0
    truth_nav = ground_truth_tables(open_logs([log], load_config().logs), ["uav1"])["uav1"]
    write_tum(RunLayout(run).fuse().trajectory("uav1"), truth_nav)
    r = cvslam("export", run, "--frame", "dataset", "--format", "euroc", "--log", log)
    assert r.code == 0, r.err
    est = file_interface.read_euroc_csv_trajectory(str(run / "export/fuse_dataset/uav1.csv"))
    ref = file_interface.read_tum_trajectory_file(
        str(mav0 / "state_groundtruth_estimate0" / "groundtruth.tum")
    )
    ref, est = sync.associate_trajectories(ref, est)
    assert est.num_poses == 95
    ape = metrics.APE(metrics.PoseRelation.full_transformation)
    ape.process_data((ref, est))
    assert ape.get_statistic(metrics.StatisticsType.max) < 1e-6  # 9 decimals in the .tum
    nav = file_interface.read_tum_trajectory_file(str(RunLayout(run).fuse().trajectory("uav1")))
    ape.process_data(sync.associate_trajectories(ref, nav))
    assert ape.get_statistic(metrics.StatisticsType.max) > 0.5  # the nav frame is another


def test_dataset_frame_of_a_log_bound_to_another_vehicle_name(tmp_path, cvslam):
    """A log imported as `car` bound to vehicle `robot` (NAME=PATH) gives robot its frame;
    without the binding there is none for robot."""
    from cvslam_cli.config import load_config
    from cvslam_cli.geometry.rotations import make_T, quat_xyzw_to_matrix
    from cvslam_cli.io.logs import ground_truth_tables, open_logs
    from tests.io.test_dataset_frames import kitti_folder

    rng = np.random.default_rng(5)
    q = rng.normal(size=(4, 4))
    Ts = np.stack(
        [make_T(quat_xyzw_to_matrix(x / np.linalg.norm(x)), rng.normal(size=3)) for x in q]
    )
    seq, log, run = kitti_folder(tmp_path / "seq", Ts), tmp_path / "car.mcap", tmp_path / "run"
    assert cvslam("-q", "import", "kitti", seq, "--vehicle", "car", "-o", log).code == 0
    truth = ground_truth_tables(open_logs([log], load_config().logs), ["car"])["car"]
    write_tum(RunLayout(run).fuse().trajectory("robot"), truth)
    r = cvslam("export", run, "--frame", "dataset", "--format", "kitti", "--log", f"robot={log}")
    assert r.code == 0, r.err
    back = read_kitti(run / "export" / "fuse_dataset" / "robot.txt")
    np.testing.assert_allclose(as_T(back), Ts, atol=1e-8)  # the .tum's 9 decimals
    r = cvslam("export", run, "--frame", "dataset", "--log", log)
    assert r.code == 1 and "vehicle robot: its logs (" in r.err and "record no dataset" in r.err
