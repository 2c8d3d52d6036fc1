"""`cvslam eval` and `cvslam run` end to end on a small simulated run: outputs, metrics that
agree with a direct computation, ground truth from files, skipping, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from cvslam_cli.evaluation.metrics import ate
from cvslam_cli.io.trajectory import read_tum, write_kitti

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _ok(res) -> None:
    assert res.code == 0, res.err


@pytest.fixture(scope="module")
def compared_run(small_image_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small run with the single and EKF comparisons fused too."""
    from cvslam_cli.cli import main

    run = tmp_path_factory.mktemp("eval") / "run"
    shutil.copytree(small_image_run, run)
    for extra in (["--single"], ["--filter", "ekf"]):
        with pytest.raises(SystemExit) as exc:
            main(["-q", "fuse", str(run), *extra])
        assert exc.value.code in (0, None)
    return run


def test_eval_writes_metrics_figures_and_report(compared_run, tmp_path, cvslam):
    run = tmp_path / "run"
    shutil.copytree(compared_run, run)
    res = cvslam("eval", run)
    _ok(res)
    out = run / "eval"
    for name in ("metrics.json", "metrics.csv", "headline.csv", "report.html"):
        assert (out / name).is_file()
    assert not (run / "eval.partial").exists()
    m = pd.read_csv(out / "metrics.csv")
    labels = set(m["estimate"])
    assert labels == {"cooperative NH-inf", "single NH-inf", "cooperative EKF", "dead reckoning"}
    assert set(m["vehicle"]) == {"uav1", "uav2"}
    # the numbers are the metrics module's on the files (ATE, no alignment)
    truth = read_tum(run / "truth" / "uav1.tum")
    row = m[(m["estimate"] == "cooperative NH-inf") & (m["vehicle"] == "uav1")].iloc[0]
    direct = ate(truth, read_tum(run / "fuse" / "uav1.tum"))
    assert row["ate_rmse_m"] == pytest.approx(direct.rmse, rel=1e-5)
    assert row["ate_max_m"] == pytest.approx(direct.max, rel=1e-5)
    # the fused estimates are far better than dead reckoning; NEES only where covariances are
    for v in ("uav1", "uav2"):
        mv = m[m["vehicle"] == v].set_index("estimate")
        assert mv.loc["cooperative NH-inf", "ate_rmse_m"] < mv.loc["dead reckoning", "ate_rmse_m"]
        assert np.isfinite(mv.loc["cooperative NH-inf", "nees_mean"])
        assert np.isnan(mv.loc["dead reckoning", "nees_mean"])
        assert 0 < mv.loc["cooperative NH-inf", "rpe_drift_pct"] < 100
    headline = pd.read_csv(out / "headline.csv", index_col=0)
    assert headline.loc["uav1", "cooperative NH-inf"] == pytest.approx(direct.rmse, rel=1e-5)
    assert "cooperative NH-inf" in res.out and "uav2" in res.out  # printed table
    js = json.loads((out / "metrics.json").read_text())
    assert js["align"] == "none" and len(js["estimates"]) == len(m)
    figs = {p.stem for p in (out / "figures").glob("*.png")}
    assert {"headline", "position_uav1", "top_view", "landmark_uncertainty", "nees"} <= figs
    assert {"error_coop_uav1", "error_filters_uav2", "feature_counts"} <= figs
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") == len(figs)
    # the metrics in one table per family, the config folded away
    for group in ("Absolute trajectory error", "Relative pose error", "Consistency: position NEES"):
        assert f"<h3>{group}" in html
    assert html.count("<details>") == 1 and "<summary>The resolved config" in html
    assert "first pose whose NEES reaches" in html  # the NEES caption says where lines start
    # rerun: skipped; --align sim3 is another config
    res = cvslam("eval", run)
    assert res.code == 0 and "up to date" in res.err
    res = cvslam("eval", run, "--align", "sim3")
    assert res.code == 1 and "eval.align" in res.err
    _ok(cvslam("-q", "eval", run, "--align", "sim3", "--force"))
    m3 = pd.read_csv(out / "metrics.csv").set_index(["estimate", "vehicle"])
    # an aligned error can only be smaller
    assert (
        m3.loc[("dead reckoning", "uav1"), "ate_rmse_m"]
        <= m.set_index(["estimate", "vehicle"]).loc[("dead reckoning", "uav1"), "ate_rmse_m"]
    )


def test_ground_truth_from_files(compared_run, tmp_path, cvslam):
    run = tmp_path / "run"
    shutil.copytree(compared_run, run)
    gt = tmp_path / "gt"
    gt.mkdir()
    shutil.copy(run / "truth" / "uav1.tum", gt / "uav1.tum")
    # KITTI (no stamps: the estimate is matched by index, so give it as many poses)
    truth2 = read_tum(run / "truth" / "uav2.tum")
    write_kitti(gt / "uav2_kitti.txt", truth2)
    _ok(cvslam("-q", "eval", run, "--gt", gt / "uav1.tum"))
    m = pd.read_csv(run / "eval" / "metrics.csv")
    assert set(m["vehicle"]) == {"uav1"}  # only the given truth
    res = cvslam("eval", run, "--gt", gt / "uav2_kitti.txt", "--force")
    assert res.code == 1 and "uav2_kitti" in res.err and "VEHICLE=FILE" in res.err
    res = cvslam("eval", run, "--gt", f"uav9={gt / 'uav1.tum'}", "--force")
    assert res.code == 1 and "uav9" in res.err
    res = cvslam("eval", run, "--gt", f"uav1={gt / 'missing.tum'}", "--force")
    assert res.code == 1 and "missing.tum" in res.err
    # truth in another time base: nothing associates -> one line naming both
    shifted = read_tum(gt / "uav1.tum")
    from cvslam_cli.io.trajectory import write_tum
    from cvslam_cli.records.poses import PoseTable

    write_tum(
        gt / "late.tum",
        PoseTable(shifted.stamps_ns + 10**12, shifted.p_nav_m, shifted.q_nav_body_xyzw),
    )
    res = cvslam("eval", run, "--gt", f"uav1={gt / 'late.tum'}", "--force")
    assert res.code == 1 and "Traceback" not in res.err
    assert "fuse/uav1.tum" in res.err and "late.tum" in res.err and "timestamps" in res.err


def test_one_vehicle_report_leaves_out_what_only_a_team_has(small_image_run, tmp_path, cvslam):
    """uav1 alone (its features only), fused alone and "single": the two runs are the same
    filter, so no single-vs-cooperative figure; no type-2 line or caption, one mosaic panel
    (the merged mosaic is the same), with its scale bar."""
    from cvslam_cli.evaluation import figures as figs

    run = tmp_path / "run"
    shutil.copytree(small_image_run, run, ignore=shutil.ignore_patterns("fuse", "uav2.npz"))
    for args in ([], ["--single"]):
        _ok(cvslam("-q", "fuse", run, *args))
    _ok(cvslam("-q", "mosaic", run, "--gsd", "1.0", "--set", "mosaic.every_nth=4"))
    _ok(cvslam("-q", "eval", run))
    out = run / "eval"
    names = {p.stem for p in (out / "figures").glob("*.png")}
    assert {"headline", "position_uav1", "feature_counts", "nees", "mosaics"} <= names
    assert not any(n.startswith("error_coop") for n in names)
    html = (out / "report.html").read_text()
    assert "single vs cooperative" not in html and "type 2" not in html
    assert "other vehicles" not in html and "merged" not in html
    mosaic_png = cv2.imread(str(out / "figures" / "mosaics.png"))
    assert mosaic_png.shape[1] == round(figs.MOSAIC_PANEL_IN[0] * figs.DPI)  # one panel
    assert "1 vehicle(s)" in html


def test_eval_needs_a_fuse_run(tmp_path, cvslam):
    res = cvslam("eval", tmp_path / "empty")
    assert res.code == 1 and "cvslam fuse" in res.err and "Traceback" not in res.err


def test_run_makes_every_stage_and_skips_them_when_unchanged(small_image_run, tmp_path, cvslam):
    logs = sorted(small_image_run.glob("*.mcap"))
    sim = tmp_path / "sim"
    sim.mkdir()
    for p in logs:
        shutil.copy(p, sim / p.name)
    shutil.copytree(small_image_run / "truth", sim / "truth")
    run = tmp_path / "run"
    res = cvslam("run", *sorted(sim.glob("*.mcap")), "-o", run, "--set", "run.comparisons=[single]")
    _ok(res)
    stages = yaml.safe_load((run / "run.yaml").read_text())["stages"]
    assert set(stages) == {"extract", "fuse", "fuse_single", "mosaic", "eval"}
    assert (run / "eval" / "report.html").is_file() and (run / "mosaic" / "all.png").is_file()
    assert "single NH-inf" in res.out and "cooperative NH-inf" in res.out
    finished = {k: v["finished"] for k, v in stages.items()}
    res = cvslam("run", *sorted(sim.glob("*.mcap")), "-o", run, "--set", "run.comparisons=[single]")
    _ok(res)
    assert res.err.count("up to date") == 5
    stages = yaml.safe_load((run / "run.yaml").read_text())["stages"]
    assert {k: v["finished"] for k, v in stages.items()} == finished


@pytest.mark.realdata
@pytest.mark.parametrize("align", ["none", "se3", "sim3"])
def test_cvslam_eval_equals_evo_on_kitti_00(shared_data, tmp_path, cvslam, align):
    """`cvslam eval` on ORB-SLAM's KITTI 00 trajectory (as a run's fuse output) with the
    KITTI ground truth file: its ATE and its RPE (consecutive poses) equal evo's APE / RPE
    (`-r trans_part`, same alignment) on the original files to 1e-6 relative."""
    import os

    os.environ.setdefault("MPLBACKEND", "Agg")
    from evo.core import metrics
    from evo.tools import file_interface

    from cvslam_cli.io.trajectory import read_kitti, write_tum

    ref_file = shared_data / "reference_trajectories" / "KITTI_00_gt.txt"
    est_file = shared_data / "reference_trajectories" / "KITTI_00_ORB.txt"
    run = tmp_path / "run"
    (run / "fuse").mkdir(parents=True)
    write_tum(run / "fuse" / "car.tum", read_kitti(est_file))
    _ok(cvslam("-q", "eval", run, "--gt", f"car={ref_file}", "--align", align))
    row = pd.read_csv(run / "eval" / "metrics.csv").set_index("estimate").loc["cooperative NH-inf"]

    ref = file_interface.read_kitti_poses_file(str(ref_file))
    est = file_interface.read_kitti_poses_file(str(est_file))
    if align != "none":
        est.align(ref, correct_scale=align == "sim3")
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, 1, metrics.Unit.frames)
    rpe.process_data((ref, est))
    a, r = ape.get_all_statistics(), rpe.get_all_statistics()
    for ours, theirs in (
        ("ate_rmse_m", a["rmse"]), ("ate_mean_m", a["mean"]), ("ate_median_m", a["median"]),
        ("ate_max_m", a["max"]), ("rpe_frame_rmse_m", r["rmse"]), ("rpe_frame_mean_m", r["mean"]),
    ):  # fmt: skip
        assert row[ours] == pytest.approx(theirs, rel=1e-6), (ours, row[ours], theirs)


def test_run_without_ground_truth_stops_before_eval(small_image_run, tmp_path, cvslam):
    """Logs with no ground truth (here: its topic mapped away): every stage that needs none
    runs, eval is skipped with a message saying how to give the truth."""
    from cvslam_cli.geometry.rotations import matrix_to_euler_zyx, quat_xyzw_to_matrix

    logs = sorted(small_image_run.glob("*.mcap"))
    run = tmp_path / "run"
    poses = []  # the initial poses a user would give in the config
    for v in ("uav1", "uav2"):
        t = read_tum(small_image_run / "truth" / f"{v}.tum")
        vel = (t.p_nav_m[1] - t.p_nav_m[0]) / ((t.stamps_ns[1] - t.stamps_ns[0]) * 1e-9)
        euler = matrix_to_euler_zyx(quat_xyzw_to_matrix(t.q_nav_body_xyzw[0]))
        fmt = lambda a: "[" + ", ".join(f"{x:.9f}" for x in a) + "]"  # noqa: E731
        poses.append(
            f"{v}: {{position_m: {fmt(t.p_nav_m[0])}, euler_rad: {fmt(euler)}, "
            f"velocity_m_s: {fmt(vel)}}}"
        )
    res = cvslam(
        "run", *logs, "-o", run,
        "--set", "logs.vehicle_defaults.topics.ground_truth=/none",
        "--set", "fuse.initial.poses={" + ", ".join(poses) + "}",
        "--set", "run.comparisons=[]", "--set", "run.mosaic=false",
    )  # fmt: skip
    _ok(res)
    assert "eval skipped" in res.err and "--gt" in res.err
    assert "no ground truth to compare with" in res.err
    assert (run / "fuse" / "uav1.tum").is_file() and not (run / "eval").exists()
