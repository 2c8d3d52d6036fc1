"""`cvslam mosaic` end to end on a small simulated run with images: outputs and world files
that place the mosaic on the true ground, coverage per vehicle and merged, run-directory
rules, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from cvslam_cli.io.mosaic_files import read_world_file

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _ok(res) -> None:
    assert res.code == 0, res.err


@pytest.fixture(scope="module")
def fused_run(small_image_run: Path) -> Path:
    return small_image_run


def _stage_summary(run: Path, name: str) -> dict:
    return yaml.safe_load((run / "run.yaml").read_text())["stages"][name]["summary"]


def _world_ncc(run: Path, folder: str, name: str) -> float:
    """NCC between a written mosaic (PNG + world file, as a GIS reads them) and the
    simulator's true ground texture sampled at the same map coordinates."""
    img = cv2.imread(str(run / folder / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert img.ndim == 3 and img.shape[2] == 4  # BGRA: alpha marks no-data
    a, d, b, e, c, f = read_world_file(run / folder / f"{name}.pgw")
    assert d == 0 and b == 0 and e == -a
    world = np.load(run / "truth" / "world.npz")
    tex, px, o = world["texture"], float(world["texture_px_per_m"]), world["origin_nav_m"]
    rows, cols = np.nonzero(img[:, :, 3] > 0)
    east, north = a * cols + c, e * rows + f  # map x = east, y = north
    ti = np.rint((north - o[0]) * px - 0.5).astype(int)
    tj = np.rint((east - o[1]) * px - 0.5).astype(int)
    inside = (ti >= 0) & (ti < tex.shape[0]) & (tj >= 0) & (tj < tex.shape[1])
    assert inside.mean() > 0.9
    ref = tex[ti[inside], tj[inside]].astype(float)
    got = img[rows[inside], cols[inside], 0].astype(float)
    return float(np.corrcoef(ref, got)[0, 1])


def test_mosaics_per_vehicle_and_merged_sit_on_the_true_ground(fused_run, tmp_path, cvslam):
    run = tmp_path / "run"
    shutil.copytree(fused_run, run)
    _ok(cvslam("-q", "mosaic", run, "--source", "groundtruth"))
    _ok(cvslam("-q", "mosaic", run))
    for folder in ("mosaic", "mosaic_groundtruth"):
        for name in ("uav1", "uav2", "all"):
            for suffix in (".png", ".pgw", "_overlay.png"):
                assert (run / folder / f"{name}{suffix}").is_file()
        assert not list(run.glob(f"{folder}*.partial"))
    gt = _stage_summary(run, "mosaic_groundtruth")
    fused = _stage_summary(run, "mosaic")
    for summary in (gt, fused):
        m = summary["mosaics"]
        assert m["uav1"]["images"] + m["uav2"]["images"] == m["all"]["images"]
        # the merged mosaic covers the union of the vehicles' areas: more than either,
        # less than both added (they overlap), and every pixel either of them covers
        areas = [m[v]["covered_m2"] for v in ("uav1", "uav2")]
        assert max(areas) < m["all"]["covered_m2"] <= sum(areas) + 1.0
        assert summary["union_coverage"] == pytest.approx(1.0)
    # with true poses the mosaic lies on the true texture to within a pixel
    for name in ("uav1", "uav2", "all"):
        t = gt["mosaics"][name]["truth"]
        assert t["shift_m"] < 2 * gt["gsd_m"], (name, t)
        assert t["ncc"] > 0.6, (name, t)
        assert t["tiles_matched"] > 0.6, (name, t)
        # fused poses: the same ground within a few pixels
        tf = fused["mosaics"][name]["truth"]
        assert tf["ncc"] > 0.5 and tf["shift_m"] < 2.0, (name, tf)
    # read back as a GIS would (PNG + world file) the mosaic matches the true ground
    assert _world_ncc(run, "mosaic_groundtruth", "all") > 0.6
    # rerun: skipped; another GSD: refused without --force
    res = cvslam("mosaic", run)
    assert res.code == 0 and "up to date" in res.err
    res = cvslam("mosaic", run, "--gsd", "0.5")
    assert res.code == 1 and "mosaic.gsd_m" in res.err


def test_every_nth_image_multiband_blend_and_fixed_gsd(fused_run, tmp_path, cvslam):
    run = tmp_path / "run"
    shutil.copytree(fused_run, run)
    _ok(
        cvslam(
            "-q", "mosaic", run, "--source", "groundtruth", "--gsd", "0.4",
            "--set", "mosaic.every_nth=4", "--set", "mosaic.blend=multiband",
            "--set", "mosaic.overlay=false",
        )
    )  # fmt: skip
    s = _stage_summary(run, "mosaic_groundtruth")
    assert s["gsd_m"] == 0.4
    frames = {
        v: len(np.load(run / "features" / f"{v}.npz")["frame_stamp_ns"]) for v in ("uav1", "uav2")
    }
    for v, n in frames.items():
        assert s["mosaics"][v]["images"] == -(-n // 4)
    assert not (run / "mosaic_groundtruth" / "all_overlay.png").exists()
    assert s["mosaics"]["all"]["truth"]["ncc"] > 0.6
    assert read_world_file(run / "mosaic_groundtruth" / "all.pgw")[0] == 0.4


def test_bad_inputs_give_one_line_errors(fused_run, tmp_path, cvslam):
    run = tmp_path / "run"
    shutil.copytree(fused_run, run)
    res = cvslam("mosaic", run, "--gsd", "-1")
    assert res.code == 1 and "--gsd" in res.err and "Traceback" not in res.err
    res = cvslam("mosaic", run, "--set", "mosaic.fuse_dir=fuse_ekf")
    assert res.code == 1 and "fuse_ekf/map.csv" in res.err and "cvslam fuse" in res.err
    res = cvslam("mosaic", tmp_path / "nothing")
    assert res.code == 1 and "no feature files" in res.err
    # a map with no ground in it: every landmark on one vertical wall
    m = (run / "fuse" / "map.csv").read_text().splitlines()
    rows = [r.split(",") for r in m[1:]]
    for i, r in enumerate(rows):
        r[1], r[2], r[3] = "10.0", str(float(i % 50)), str(-float(i // 50))
    (run / "fuse" / "map.csv").write_text("\n".join([m[0], *(",".join(r) for r in rows)]) + "\n")
    res = cvslam("mosaic", run)
    assert res.code == 1 and "map.csv" in res.err and "ground" in res.err
    assert not (run / "mosaic").exists() and not (run / "mosaic.partial").exists()
