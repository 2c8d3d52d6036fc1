"""`cvslam refine` end to end on a small simulated two-UAV run (landmark mode, the filter's
own observations): outputs in the fuse formats, picked up by eval, better than the filter,
the gauge reported; `cvslam run` with run.comparisons [refined]; bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cvslam_cli.io.fuse_files import load_pose_covariances, read_map_csv
from cvslam_cli.io.observations_file import load_observations
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.trajectory import read_tum
from tests.scenarios import small_uav_scenario

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

CAMERA = {"width": 376, "height": 240, "fx": 225.0, "fy": 225.0, "cx": 187.5, "cy": 119.5}


@pytest.fixture(scope="module")
def fused(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 s of the small two-UAV scenario in landmark mode, simulated and fused once."""
    from cvslam_cli.cli import main

    tmp = tmp_path_factory.mktemp("refine")
    sc = small_uav_scenario(
        tmp,
        duration_s=8.0,
        mode="landmarks",
        **{f"vehicles.{v}.camera.{k}": x for v in ("uav1", "uav2") for k, x in CAMERA.items()},
    )
    run = tmp / "run"
    for args in (["-q", "simulate", str(sc), "-o", str(run)], ["-q", "fuse", str(run)]):
        with pytest.raises(SystemExit) as exc:
            main(args)
        assert exc.value.code in (0, None), args
    return run


def _copy(run: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(run, out)
    return out


def test_fuse_writes_the_observations_it_used(fused):
    obs = load_observations(fused / "fuse" / "observations.npz")
    lm = read_map_csv(fused / "fuse" / "map.csv")
    assert obs.vehicles == ("uav1", "uav2")
    assert set(np.unique(obs.landmark_id)) <= set(lm.landmark_id)
    # every landmark's observation count in the map is the observations recorded of it
    ids, counts = np.unique(obs.landmark_id, return_counts=True)
    n_obs = dict(zip(lm.landmark_id.tolist(), lm.n_observations.tolist(), strict=True))
    assert all(n_obs[i] == c for i, c in zip(ids.tolist(), counts.tolist(), strict=True))
    # the measurements are pixels inside the images
    assert np.all((obs.z_px[:, [0, 2]] > -1) & (obs.z_px[:, [0, 2]] < CAMERA["width"] + 1))


def test_refine_writes_fuse_formats_beats_the_filter_and_reports_the_gauge(fused, tmp_path, cvslam):
    run = _copy(fused, tmp_path)
    reassociate = ("--set", "refine.reassociation.rounds=1")
    r = cvslam("refine", run, *reassociate)
    assert r.code == 0, r.err
    out = run / "fuse_refined"
    for v in ("uav1", "uav2"):
        table = read_tum(out / f"{v}.tum")
        st, cov = load_pose_covariances(out / f"{v}_pose_cov.npz")
        assert np.array_equal(st, table.stamps_ns)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        assert (out / f"{v}_deadreckoning.tum").exists()
    for name in ("map.csv", "map.ply", "result.mcap", "fuse.config.yaml"):
        assert (out / name).exists(), name
    # every landmark of the filter's map, and re-association's new points after them
    ids = read_map_csv(out / "map.csv").landmark_id
    src_ids = read_map_csv(run / "fuse" / "map.csv").landmark_id
    assert np.array_equal(ids[: len(src_ids)], src_ids)
    assert len(ids) > len(src_ids) and ids[len(src_ids) :].min() > src_ids.max()
    summary = RunDir(run).load()["stages"]["fuse_refined"]["summary"]
    assert "first keyframe" in summary["gauge"]
    for v, s in summary["vehicles"].items():
        assert s["rmse_m"] < s["rmse_source_m"], v
        assert s["prior_sigma_position_m"] > 0
    assert "gauge: prior on the first keyframe" in r.err
    r = cvslam("eval", run)
    assert r.code == 0, r.err
    metrics = pd.read_csv(run / "eval" / "metrics.csv")
    refined = metrics[metrics.run == "fuse_refined"]
    assert set(refined.vehicle) == {"uav1", "uav2"}
    assert refined.nees_mean.notna().all()
    head = pd.read_csv(run / "eval" / "headline.csv", index_col=0)
    assert "refined" in head.columns
    assert (head["refined"] < head["cooperative NH-inf"]).all()
    # rerun: up to date
    r = cvslam("refine", run, *reassociate)
    assert r.code == 0 and "up to date" in r.err


def test_refine_without_observations_says_what_to_run(fused, tmp_path, cvslam):
    run = _copy(fused, tmp_path)
    (run / "fuse" / "observations.npz").unlink()
    r = cvslam("refine", run)
    assert r.code == 1
    assert "observations.npz" in r.err and "cvslam fuse --force" in r.err
    assert "Traceback" not in r.err
    assert not (run / "fuse_refined").exists()
    r = cvslam("refine", run, "--source", "fuse_ekf")
    assert r.code == 1 and "fuse_ekf" in r.err and "cvslam fuse" in r.err


def test_run_makes_the_refined_comparison(small_image_run, tmp_path, cvslam):
    """Images (extract's features, its pixel noise), keyframes every second frame; the
    filter's observations only (run's plumbing is tested here, re-association above)."""
    run = _copy(small_image_run, tmp_path)
    logs = sorted(run.glob("*.mcap"))
    r = cvslam(
        "run", *logs, "-o", run, "--set", "run.comparisons=[refined]", "--set",
        "run.mosaic=false", "--set", "refine.every_nth=2", "--set",
        "refine.reassociation.rounds=0",
    )  # fmt: skip
    assert r.code == 0, r.err
    head = pd.read_csv(run / "eval" / "headline.csv", index_col=0)
    assert "refined" in head.columns
    n_fuse = len(read_tum(run / "fuse" / "uav1.tum"))
    # every second frame a keyframe, and the last
    assert len(read_tum(run / "fuse_refined" / "uav1.tum")) == len(range(0, n_fuse, 2)) + (
        (n_fuse - 1) % 2
    )
    summary = RunDir(run).load()["stages"]["fuse_refined"]["summary"]
    assert summary["pixel_sigma_px"] == 0.3  # extract.stereo.pixel_sigma_px
    r = cvslam(
        "mosaic", run, "--set", "mosaic.fuse_dir=fuse_refined", "--set", "mosaic.overlay=false"
    )
    assert r.code == 0, r.err
    assert (run / "mosaic" / "all.png").exists()
