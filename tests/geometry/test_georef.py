"""Georeferencing of nav-frame rasters: the local map, and UTM checked against pyproj's own
projection of the origin and its scale factor and grid convergence there."""

from __future__ import annotations

import math

import numpy as np
import pyproj
import pytest

from cvslam_cli.geometry.georef import (
    LOCAL_CRS_WKT,
    local_placement,
    nav_to_geodetic,
    scale_bar_m,
    topocentric_en,
    utm_epsg,
    utm_placement,
)

# (lat, lon, alt): west of a central meridian (north), south hemisphere east of one, a
# high latitude (large convergence)
ORIGINS = [(45.5, 7.5, 300.0), (-33.9, 18.4, 20.0), (69.6, 18.9, 10.0)]
BOX = (-300.0, -400.0, 500.0, 600.0)  # n_min, e_min, n_max, e_max [m]
EARTH_RADIUS_M = 6371e3  # mean: the radii of curvature differ by < 1 %, 0.05 mm here


def _utm_of(lat: float, lon: float) -> tuple[pyproj.Transformer, pyproj.Proj]:
    epsg = utm_epsg(lat, lon)
    return pyproj.Transformer.from_crs(4326, epsg, always_xy=True), pyproj.Proj(epsg)


def test_local_map_is_nav_east_north_in_metres():
    p = local_placement()
    assert p.crs_wkt == LOCAL_CRS_WKT and pyproj.CRS.from_wkt(p.crs_wkt).is_engineering
    axes = pyproj.CRS.from_wkt(p.crs_wkt).axis_info
    assert [a.direction for a in axes] == ["east", "north"]
    assert all(a.unit_name == "metre" for a in axes)
    # top-left corner (n 120, e -40), 0.25 m pixels: x east grows with columns, y north
    # falls with rows
    assert p.raster_transform(120.0, -40.0, 0.25) == (0.25, 0.0, -40.0, 0.0, -0.25, 120.0)
    assert np.allclose(p.map_xy(np.array([1.0, 2.0]), np.array([3.0, 4.0])), [[3, 1], [4, 2]])


@pytest.mark.parametrize(("lat", "lon", "epsg"), [
    (45.5, 7.5, 32632), (-33.9, 18.4, 32734), (0.0, -180.0, 32601), (10.0, 180.0, 32601),
    (-0.1, 179.9, 32760), (51.0, -0.1, 32630),
])  # fmt: skip
def test_utm_zone_of_the_origin(lat, lon, epsg):
    assert utm_epsg(lat, lon) == epsg


@pytest.mark.parametrize(("lat", "lon", "alt"), ORIGINS)
@pytest.mark.parametrize("heading_deg", [0.0, 30.0, -120.0])
def test_utm_places_the_origin_and_nav_directions_as_pyproj(lat, lon, alt, heading_deg):
    p = utm_placement(lat, lon, alt, heading_deg, BOX)
    to_utm, proj = _utm_of(lat, lon)
    assert p.crs_name.startswith(f"EPSG:{utm_epsg(lat, lon)}")
    assert pyproj.CRS.from_wkt(p.crs_wkt).to_epsg() == utm_epsg(lat, lon)
    # the nav origin is at pyproj's UTM easting/northing of its latitude and longitude
    x0, y0 = to_utm.transform(lon, lat)
    assert np.allclose(p.map_xy(0.0, 0.0), [x0, y0], rtol=0, atol=1e-3)
    # 100 m along nav x (true azimuth = heading) and along nav y (heading + 90 degrees):
    # UTM's grid azimuth is the true one less the meridian convergence there, the
    # distance is scaled by the point scale factor (pyproj's factors at the origin) and
    # by R / (R + alt) from the origin's height down to the ellipsoid
    f = proj.get_factors(lon, lat)
    gamma = f.meridian_convergence
    k = f.meridional_scale * EARTH_RADIUS_M / (EARTH_RADIUS_M + alt)
    for (dn, de), azimuth in (((100.0, 0.0), heading_deg), ((0.0, 100.0), heading_deg + 90.0)):
        d = p.map_xy(dn, de) - p.map_xy(0.0, 0.0)
        grid_az = math.radians(azimuth - gamma)
        expected = 100.0 * k * np.array([math.sin(grid_az), math.cos(grid_az)])
        assert np.allclose(d, expected, rtol=0, atol=2e-3), (d, expected)
    # with heading 0, 100 m north of the origin is 100 m north in UTM up to the grid
    # convergence and the scale factor: bounded by them
    if heading_deg == 0.0:
        d = p.map_xy(100.0, 0.0) - p.map_xy(0.0, 0.0)
        bound = 100.0 * (abs(math.radians(gamma)) + abs(k - 1.0)) + 1e-3
        assert bound < 100.0 * math.radians(2.5)  # convergence below 2 degrees here
        assert np.linalg.norm(d - [0.0, 100.0]) <= bound
    # the affine is the exact mapping to a few millimetres over a kilometre (the scale
    # factor changes across the box, the more the farther from the central meridian)
    assert p.max_fit_error_m < 5e-3


def test_utm_fit_error_bounds_the_affine_against_the_exact_mapping():
    box = (-20e3, -20e3, 20e3, 20e3)
    small = utm_placement(45.5, 7.5, 300.0, 10.0, BOX)
    large = utm_placement(45.5, 7.5, 300.0, 10.0, box)
    assert small.max_fit_error_m < 1e-3 < large.max_fit_error_m < 2.0  # 1.2 m over 40 km
    # at points off the fit's grid, the affine is within the reported error (and a margin
    # for points between the samples) of the exact tangent-plane -> UTM mapping
    rng = np.random.default_rng(0)
    n, e = rng.uniform(-20e3, 20e3, 50), rng.uniform(-20e3, 20e3, 50)
    to_utm, _ = _utm_of(45.5, 7.5)
    lon, lat, _ = nav_to_geodetic(45.5, 7.5, 300.0).transform(
        *topocentric_en(n, e, 10.0), np.zeros_like(n)
    )
    exact = np.c_[to_utm.transform(lon, lat)]
    assert np.max(np.linalg.norm(large.map_xy(n, e) - exact, axis=1)) < 1.5 * large.max_fit_error_m


def test_raster_transform_places_pixel_corners_through_the_map():
    p = utm_placement(45.5, 7.5, 300.0, 25.0, BOX)
    a, b, c, d, e, f = p.raster_transform(500.0, -400.0, 0.5)
    for col, row in ((0, 0), (10, 0), (0, 7), (123, 45)):
        x, y = a * col + b * row + c, d * col + e * row + f
        assert np.allclose([x, y], p.map_xy(500.0 - 0.5 * row, -400.0 + 0.5 * col), atol=1e-6)


@pytest.mark.parametrize(("span", "bar"), [
    (1.0, 0.2), (3.9, 0.5), (4.0, 1.0), (99.0, 20.0), (250.0, 50.0), (1e4, 2000.0), (0.03, 0.005),
])  # fmt: skip
def test_scale_bar_is_a_round_length_at_most_a_quarter_of_the_width(span, bar):
    assert scale_bar_m(span) == pytest.approx(bar)
    assert scale_bar_m(span) <= span / 4 * (1 + 1e-9)
