"""`cvslam mosaic` end to end on a small simulated run with images: outputs and world files
that place the mosaic on the true ground, coverage per vehicle and merged, run-directory
rules, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pyproj
import pytest
import rasterio
import yaml
from rasterio.transform import Affine

from cvslam_cli.geometry.georef import LOCAL_CRS_NAME, local_placement
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
    # beside each PNG its GeoTIFF (local CRS, the PNG's pixels, the world file's transform),
    # and the overlays have the mosaic's world file
    for folder in ("mosaic", "mosaic_groundtruth"):
        for name in ("uav1", "uav2", "all"):
            crs, _ = _geotiff_matches_png(run / folder, name)
            assert LOCAL_CRS_NAME in crs.to_wkt() and crs.to_epsg() is None
            overlay = read_world_file(run / folder / f"{name}_overlay.pgw")
            assert overlay == read_world_file(run / folder / f"{name}.pgw")
            assert (run / folder / f"{name}_overlay.png.aux.xml").is_file()
    assert fused["map"] == {"crs": local_placement().crs_name, "max_fit_error_m": 0.0}
    # rerun: skipped; another GSD: refused without --force
    res = cvslam("mosaic", run)
    assert res.code == 0 and "up to date" in res.err
    res = cvslam("mosaic", run, "--gsd", "0.5")
    assert res.code == 1 and "mosaic.gsd_m" in res.err


def _geotiff_matches_png(folder: Path, name: str) -> tuple[rasterio.crs.CRS, Affine]:
    """(CRS, transform) of `<name>.tif`, checked to hold the PNG's pixels and the world
    file's transform."""
    bgra = cv2.imread(str(folder / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    A, D, B, E, C, F = read_world_file(folder / f"{name}.pgw")
    with rasterio.open(folder / f"{name}.tif") as ds:
        rgba = np.moveaxis(ds.read(), 0, -1)
        t, crs = ds.transform, ds.crs
    assert np.array_equal(rgba, bgra[..., [2, 1, 0, 3]])
    assert np.allclose([t.a, t.d, t.b, t.e], [A, D, B, E], rtol=0, atol=1e-9)
    assert np.allclose(t @ (0.5, 0.5), (C, F), rtol=0, atol=1e-6)
    return crs, t


def _apply(t: Affine, col: np.ndarray | float, row: np.ndarray | float) -> np.ndarray:
    """(2, ...) map coordinates of pixel corner coordinates (col, row)."""
    return np.array([t.a * col + t.b * row + t.c, t.d * col + t.e * row + t.f])


def test_origin_puts_the_mosaics_in_utm(fused_run, tmp_path, cvslam):
    """With the nav origin's latitude, longitude, height and heading, the GeoTIFFs and world
    files are in UTM: every pixel lies at the easting/northing pyproj gives for its nav
    position (tangent plane at the origin, turned by the heading), independently of
    cvslam's georef module."""
    run = tmp_path / "run"
    shutil.copytree(fused_run, run)
    _ok(cvslam("-q", "mosaic", run, "--source", "groundtruth", "--set", "mosaic.overlay=false"))
    out = run / "mosaic_groundtruth"
    _, t_local = _geotiff_matches_png(out, "all")
    local_png = cv2.imread(str(out / "all.png"), cv2.IMREAD_UNCHANGED)
    lat, lon, alt, heading = -33.9, 18.4, 120.0, 30.0
    origin = f"{lat},{lon},{alt},{heading}"
    res = cvslam("mosaic", run, "--source", "groundtruth", "--origin", origin)
    assert res.code == 1 and "geo.origin" in res.err and "--force" in res.err  # other config
    _ok(cvslam("-q", "mosaic", run, "--source", "groundtruth", "--origin", origin, "--force"))
    res = cvslam("mosaic", run, "--source", "groundtruth")  # back without it: another config
    assert res.code == 1 and "geo.origin" in res.err and "--force" in res.err
    crs, t_utm = _geotiff_matches_png(out, "all")
    assert crs.to_epsg() == 32734  # WGS 84 / UTM zone 34S
    assert np.array_equal(cv2.imread(str(out / "all.png"), cv2.IMREAD_UNCHANGED), local_png)
    summary = _stage_summary(run, "mosaic_groundtruth")
    assert (
        summary["map"]["crs"].startswith("EPSG:32734") and summary["map"]["max_fit_error_m"] < 0.01
    )
    # the exact mapping of nav (north, east, at the ground's height) to UTM, with pyproj
    h = np.radians(heading)
    rows, cols = np.meshgrid(
        [0, local_png.shape[0] // 2, local_png.shape[0]], [0, local_png.shape[1]]
    )
    east, north = _apply(t_local, cols.ravel(), rows.ravel())  # nav east/north of pixel corners
    ground_up = float(np.median(np.load(run / "truth" / "world.npz")["elevation_m"]))
    to_geo = pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 "
        f"+lat_0={lat} +lon_0={lon} +h_0={alt} +step +inv +proj=cart +ellps=WGS84 "
        "+step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )
    true_e = north * np.sin(h) + east * np.cos(h)
    true_n = north * np.cos(h) - east * np.sin(h)
    glon, glat, _ = to_geo.transform(true_e, true_n, np.full_like(true_e, ground_up))
    x, y = pyproj.Transformer.from_crs(4326, 32734, always_xy=True).transform(glon, glat)
    got = _apply(t_utm, cols.ravel(), rows.ravel())
    # within a centimetre: the affine fit (mm) and one ground height for the whole mosaic
    assert np.max(np.hypot(got[0] - x, got[1] - y)) < 0.01
    # the origin itself is at pyproj's UTM of its latitude and longitude, moved by the
    # ground's height (a few mm at most here)
    x0, y0 = pyproj.Transformer.from_crs(4326, 32734, always_xy=True).transform(lon, lat)
    col0, row0 = _apply(~t_local, 0.0, 0.0)
    assert np.hypot(*(_apply(t_utm, col0, row0) - (x0, y0))) < 0.01


@pytest.mark.parametrize(("origin", "message"), [
    ("95,7,0,0", "geo.origin.lat_deg"), ("45,7,0", "--origin 45,7,0: expected LAT,LON,ALT,HEADING"),
    ("45,7,x,0", "--origin"), ("45,7,0,nan", "geo.origin.heading_deg"),
])  # fmt: skip
def test_bad_origin_is_one_line_naming_the_key(fused_run, tmp_path, cvslam, origin, message):
    for cmd in (["mosaic", fused_run], ["run", tmp_path / "none.mcap", "-o", tmp_path / "r"]):
        res = cvslam(*cmd, "--origin", origin)
        assert res.code == 1 and message in res.err, res.err
        assert "Traceback" not in res.err and len(res.err.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()


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
