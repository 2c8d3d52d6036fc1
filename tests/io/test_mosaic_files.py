"""Mosaic files: world files placing pixel centres, PNG with alpha, GeoTIFFs with the PNG's
pixels and the world file's transform and a CRS (read back with rasterio, as a GIS would),
bad world files."""

from __future__ import annotations

import cv2
import numpy as np
import pyproj
import pytest
import rasterio
import rasterio.errors
from rasterio.enums import ColorInterp
from rasterio.warp import calculate_default_transform

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.georef import LOCAL_CRS_NAME, local_placement, utm_placement
from cvslam_cli.io.mosaic_files import (
    read_world_file,
    write_crs_sidecar,
    write_geotiff_atomic,
    write_png_atomic,
    write_world_file,
)


def test_world_file_places_pixel_centres_in_east_north(tmp_path):
    path = tmp_path / "m.pgw"
    write_world_file(path, local_placement().raster_transform(n_max=120.0, e_min=-40.0, gsd_m=0.25))
    a, d, b, e, c, f = read_world_file(path)
    assert (a, d, b, e) == (0.25, 0.0, 0.0, -0.25)
    # pixel (col 0, row 0) centre: 0.125 m east of the west edge, 0.125 m south of the top
    assert (c, f) == (-39.875, 119.875)
    col, row = 8, 4
    assert (a * col + b * row + c, d * col + e * row + f) == (-37.875, 118.875)
    assert not list(tmp_path.glob("*.partial"))


def test_png_with_alpha_from_the_mask(tmp_path):
    img = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    mask = img > 50
    write_png_atomic(tmp_path / "m.png", img, mask)
    back = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    assert back.shape == (3, 4, 4)
    assert (back[:, :, 3] == np.where(mask, 255, 0)).all()
    assert (back[:, :, 0] == img).all() and (back[:, :, 2] == img).all()


@pytest.mark.parametrize("text", ["1\n0\n0\n-1\n5\n", "1\n0\nx\n-1\n5\n6\n"])
def test_bad_world_file_names_the_file(tmp_path, text):
    path = tmp_path / "bad.pgw"
    path.write_text(text)
    with pytest.raises(CvslamError, match=r"bad\.pgw"):
        read_world_file(path)


def _mosaic(rng: np.random.Generator, colour: bool) -> tuple[np.ndarray, np.ndarray]:
    shape = (37, 53, 3) if colour else (37, 53)
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    mask = rng.random((37, 53)) > 0.3
    return image, mask


@pytest.mark.parametrize("colour", [False, True])
@pytest.mark.parametrize("utm", [False, True])
@pytest.mark.filterwarnings("ignore:Use `@` matmul:PendingDeprecationWarning")  # rasterio's own
def test_geotiff_has_the_png_pixels_the_world_file_transform_and_the_crs(tmp_path, colour, utm):
    rng = np.random.default_rng(5)
    image, mask = _mosaic(rng, colour)
    placement = (
        utm_placement(45.5, 7.5, 300.0, 30.0, (-100.0, -50.0, 100.0, 80.0))
        if utm
        else local_placement()
    )
    transform = placement.raster_transform(n_max=95.5, e_min=-42.25, gsd_m=0.5)
    png, pgw, tif = tmp_path / "m.png", tmp_path / "m.pgw", tmp_path / "m.tif"
    write_png_atomic(png, image, mask)
    write_world_file(pgw, transform)
    write_crs_sidecar(png, placement.crs_wkt)
    write_geotiff_atomic(tif, image, mask, transform, placement.crs_wkt)
    assert not list(tmp_path.glob("*.partial"))
    bgra = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    A, D, B, E, C, F = read_world_file(pgw)
    with rasterio.open(tif) as ds:
        assert (ds.count, ds.height, ds.width) == (4, *mask.shape)
        assert ds.colorinterp[3] == ColorInterp.alpha
        rgba = np.moveaxis(ds.read(), 0, -1)
        t = ds.transform
        crs = ds.crs
    assert np.array_equal(rgba, bgra[..., [2, 1, 0, 3]])  # the PNG's pixels, RGBA
    # the world file's six numbers: pixel sizes and rotation, the top-left pixel's centre
    assert np.allclose([t.a, t.d, t.b, t.e], [A, D, B, E], rtol=0, atol=1e-10)
    assert np.allclose(t @ (0.5, 0.5), (C, F), rtol=0, atol=1e-6)
    if utm:
        assert crs.to_epsg() == 32632
        assert abs(t.b) > 0.1 * abs(t.a)  # heading 30 degrees: a rotated grid
    else:
        assert crs.to_epsg() is None and LOCAL_CRS_NAME in crs.to_wkt()
        axes = pyproj.CRS.from_wkt(crs.to_wkt()).axis_info
        assert [(a.direction, a.unit_name) for a in axes] == [("east", "metre"), ("north", "metre")]
        # GDAL's warper refuses to put the local metres on a geodetic CRS (no silent degrees)
        with pytest.raises(rasterio.errors.CRSError):
            calculate_default_transform(crs, "EPSG:4326", 53, 37, 0.0, 0.0, 26.5, 18.5)
    # GDAL reads the PNG with its world file and its CRS sidecar as the same raster
    # (GeoTIFF's keys keep a local CRS's name, unit and axes, not its datum's name)
    with rasterio.open(png) as ds:
        assert ds.crs.to_epsg() == crs.to_epsg()
        assert pyproj.CRS.from_wkt(ds.crs.to_wkt()).name == pyproj.CRS.from_wkt(crs.to_wkt()).name
        assert np.allclose(tuple(ds.transform)[:6], tuple(t)[:6], rtol=0, atol=1e-6)
