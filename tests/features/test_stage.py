"""`cvslam extract` end to end: simulated logs with true depth, run-directory rules, bad input."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import CvslamError, LogError
from cvslam_cli.features.stage import STATS_COLUMNS, run
from cvslam_cli.geometry.projection import project_points, undistort_pixels
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.mcap_writer import LogWriter
from cvslam_cli.sim.scenario import load_scenario
from cvslam_cli.sim.stage import run as simulate
from tests.scenarios import small_uav_scenario
from tests.synth import camera, write_stereo_log

CAMERA = {"width": 376, "height": 240, "fx": 225.0, "fy": 225.0, "cx": 187.5, "cy": 119.5}


def _sim(tmp: Path, rectified: bool) -> Path:
    sets = ["outputs.depth=true", "duration_s=2.0", "terrain.texture_px_per_m=4.0"]
    for v in ("uav1", "uav2"):
        sets += [f"vehicles.{v}.camera.{k}={val}" for k, val in CAMERA.items()]
        sets.append(f"vehicles.{v}.camera.rectified={str(rectified).lower()}")
    sc = load_scenario(small_uav_scenario(tmp), sets)
    return simulate(sc, tmp / "sim", workers=1).out_dir


@pytest.fixture(scope="module", params=[True, False], ids=["rectified", "unrectified"])
def extracted(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("extract")
    sim = _sim(tmp, request.param)
    logs = [sim / "uav1.mcap", sim / "uav2.mcap"]
    summary = run(load_config(), logs, tmp / "run", workers=2)
    return sim, logs, tmp / "run", summary


def _depth_frames(sim: Path, vehicle: str) -> list[np.ndarray]:
    with np.load(sim / "truth" / f"{vehicle}_depth.npz") as npz:
        return [npz[k].astype(float) for k in sorted(npz.files)]


def test_matches_against_true_correspondences(extracted):
    sim, logs, run_dir, summary = extracted
    assert set(summary.vehicles) == {"uav1", "uav2"}
    rig = LogSet([McapLogSource(p) for p in logs], load_config().logs).rig("uav1")
    fs, _ = load_features(run_dir / "features" / "uav1.npz")
    depths = _depth_frames(sim, "uav1")
    assert fs.n_frames == len(depths) == 11
    correct = total = recall_num = recall_den = 0
    z_norm = []
    for i, depth in enumerate(depths):
        sl = slice(fs.left_offsets[i], fs.left_offsets[i + 1])
        sr = slice(fs.right_offsets[i], fs.right_offsets[i + 1])
        uv_l = fs.left_uv_raw_px[sl].astype(float)
        uv_r = fs.right_uv_raw_px[sr].astype(float)
        # true position of every left keypoint in the right image (depth from the renderer)
        r, c = (
            np.clip(np.rint(uv_l[:, 1]).astype(int), 0, depth.shape[0] - 1),
            np.clip(np.rint(uv_l[:, 0]).astype(int), 0, depth.shape[1] - 1),
        )
        z = depth[r, c]
        xy = undistort_pixels(rig.left, uv_l)
        p_left = np.column_stack([xy * z[:, None], z])
        T_rl = np.linalg.inv(rig.T_left_right)
        pred, _ = project_points(rig.right, p_left @ T_rl[:3, :3].T + T_rl[:3, 3])
        near = np.linalg.norm(pred[:, None, :] - uv_r[None, :, :], axis=2).min(axis=1) < 1.5
        m = fs.frame_matches(i)
        li = fs.match_left[m] - fs.left_offsets[i]
        ri = fs.match_right[m] - fs.right_offsets[i]
        ok = np.linalg.norm(pred[li] - uv_r[ri], axis=1) < 2.0
        correct += int(ok.sum())
        total += len(li)
        recall_den += int(near.sum())
        recall_num += int((ok & near[li]).sum())
        # depth error against the covariance, for correct matches
        zt = p_left[li[ok], 2]
        zz = fs.match_p_cam_m[m][ok, 2]
        sz = np.sqrt(fs.match_cov_cam_m2[m][ok, 2, 2])
        z_norm.extend((zz - zt) / sz)
    precision = correct / total
    recall = recall_num / recall_den
    print(
        f"\nprecision {precision:.4f} ({total} matches), recall {recall:.3f}, "
        f"normalised depth error std {np.std(z_norm):.2f}"
    )
    assert total > 11 * 30
    assert precision >= 0.98
    assert recall > 0.3
    assert 0.4 < np.std(z_norm) < 2.0  # depth errors consistent with the covariance


def test_stats_csv_and_run_yaml(extracted):
    _, _, run_dir, summary = extracted
    with (run_dir / "features" / "uav2_stats.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == STATS_COLUMNS and len(rows) == 6  # uav2 starts 1 s later
    assert all(int(r["kp_left"]) > 0 and int(r["points"]) > 0 for r in rows)
    assert all(2 <= int(r["layers_left"]) <= 6 for r in rows)
    v = summary.vehicles["uav1"]
    assert v.frames == 11 and v.candidates_per_keypoint < 0.03 * v.keypoints_per_frame
    import yaml

    record = yaml.safe_load((run_dir / "run.yaml").read_text())["stages"]["extract"]
    assert record["status"] == "complete" and len(record["inputs"]) == 2
    assert all(len(i["sha256"]) == 64 for i in record["inputs"])
    assert record["config"]["extract"]["stereo"]["dist_ratio"] == 0.7


def test_rerun_skips_refuses_other_config_and_forces(extracted):
    _, logs, run_dir, _ = extracted
    before = (run_dir / "features" / "uav1.npz").stat().st_mtime_ns
    assert run(load_config(), logs, run_dir).skipped
    assert (run_dir / "features" / "uav1.npz").stat().st_mtime_ns == before
    other = load_config(overrides=["extract.stereo.dist_ratio=0.6"])
    with pytest.raises(
        CvslamError,
        match=r"different config \(extract\.stereo\.dist_ratio: "
        r"0\.7 -> 0\.6\); use --force",
    ):
        run(other, logs, run_dir)
    assert not run(other, logs, run_dir, force=True, workers=1).skipped
    assert run(other, logs, run_dir).skipped


def test_empty_constant_and_one_sided_frames(tmp_path):
    path = tmp_path / "flat.mcap"
    with LogWriter(path) as lw:
        for i in range(4):
            st = 10**9 + i * 50_000_000
            for side in ("left", "right"):
                cam = camera(64, 48, 50.0, right=side == "right", frame_id=f"v/{side}")
                lw.write_camera_info(f"/v/stereo/{side}/camera_info", st, cam)
                if side == "right" and i == 2:
                    continue  # missing right image
                img = np.zeros((48, 64), np.uint8) if i == 0 else np.full((48, 64), 128, np.uint8)
                lw.write_image(f"/v/stereo/{side}/image_raw", st, img, f"v/{side}")
    summary = run(load_config(), [path], tmp_path / "run", workers=1)
    v = summary.vehicles["v"]
    assert (v.frames, v.empty_frames, v.unpaired_left) == (3, 3, 1)
    fs, _ = load_features(tmp_path / "run" / "features" / "v.npz")
    assert fs.n_frames == 3 and fs.left_offsets[-1] == 0 and fs.match_offsets[-1] == 0


def test_calibration_inconsistent_with_images(tmp_path):
    synth = write_stereo_log(tmp_path / "a.mcap", size=(64, 48), info_size=(80, 60))
    with pytest.raises(LogError, match="image is 64x48 but its calibration"):
        run(load_config(), [synth.path], tmp_path / "run", workers=1)
    assert not (tmp_path / "run" / "features" / "uav1.npz").exists()


@pytest.mark.parametrize(
    "dataset, depth_range_m, min_fraction",
    [
        ("euroc", (0.5, 15.0), 0.93),
        ("kitti", (2.0, 100.0), 0.75),
    ],
)
def test_real_data_matches_are_epipolar_and_plausible(
    shared_data, tmp_path, dataset, depth_range_m, min_fraction
):
    """Real logs through import + extract: matches lie on their epipolar lines and their
    depths fit the scene (EuRoC: a room; KITTI: a street). KITTI's rectification leaves
    ~0.6 px of vertical scatter even for plain SIFT, hence its lower fraction under 1 px."""
    from cvslam_cli.geometry.camera import stereo_rig
    from cvslam_cli.io.importers.euroc import import_euroc
    from cvslam_cli.io.importers.kitti import import_kitti
    from tests.features.reference_matcher import epipolar_residual_px

    log = tmp_path / f"{dataset}.mcap"
    if dataset == "euroc":
        import_euroc(shared_data / "euroc_v101_micro" / "mav0", log, "uav1")
    else:
        import_kitti(shared_data / "kitti_clip_a", log, "uav1")
    run(load_config(), [log], tmp_path / "run", workers=2)
    fs, _ = load_features(tmp_path / "run" / "features" / "uav1.npz")
    rig = stereo_rig(fs.rig)
    res = epipolar_residual_px(rig, fs.left_uv_px[fs.match_left], fs.right_uv_px[fs.match_right])
    z = fs.match_p_cam_m[:, 2]
    per_frame = np.diff(fs.match_offsets)
    print(
        f"\n{dataset}: {per_frame.mean():.0f} matches per frame (min {per_frame.min()}), "
        f"{np.mean(res < 1.0):.3f} under 1 px epipolar residual, median depth "
        f"{np.median(z):.1f} m, {np.mean((z > depth_range_m[0]) & (z < depth_range_m[1])):.3f}"
        f" in {depth_range_m} m"
    )
    assert per_frame.min() >= 50
    assert np.mean(res < 1.0) >= min_fraction and np.all(res < 1.6)
    assert np.mean((z > depth_range_m[0]) & (z < depth_range_m[1])) > 0.85
    assert np.mean(fs.match_disparity_px > 0) > 0.99  # in front: positive disparity
