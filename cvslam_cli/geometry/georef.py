"""Where a north-up raster of the nav frame lies on a map: its CRS and the affine transform
from pixels to map coordinates, and a round length for its scale bar (docs/mosaic.md).

cvslam's mosaics are north-up in the nav frame (NED): pixel columns run east (nav y), rows
run south (-nav x). Two placements:

- **local** (no `geo.origin`): an engineering CRS (`LOCAL_CRS_WKT`, WKT 1 LOCAL_CS) whose
  axes are the nav frame's east and north, in metres from the nav origin. Nothing ties it to
  the Earth; GIS tools keep it apart from geodetic layers instead of reading the metres as
  degrees.
- **UTM** (with `geo.origin`: the nav origin's latitude, longitude, ellipsoidal height and
  the heading of the nav x axis): the nav frame is taken as the local tangent plane at the
  origin, its x axis `heading_deg` clockwise from true north. A nav point (north n, east e)
  at the height of the raster's ground goes through PROJ's topocentric conversion to
  geodetic coordinates and the UTM zone of the origin (WGS 84, EPSG 326zz north / 327zz
  south); the map is the least-squares affine fit of that exact mapping over the raster's
  extent. The fit rotates the grid by the heading less the grid convergence, scales it by
  the UTM scale factor (0.9996 on the central meridian, ~1.0004 at the zone's edge) times
  R / (R + h) (the ground h above the ellipsoid: 1.6e-5 per 100 m) and is within
  millimetres of the exact mapping over a few kilometres (`max_fit_error_m` says how far,
  for the extent it was fitted on).

One height is used for the whole raster (the ground at its centre): ground 100 m higher or
lower than that moves by 1.6 cm per kilometre from the centre (the tilt of the vertical,
1/6371 km^-1, and the scale above).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyproj

from cvslam_cli.records.arrays import F64

LOCAL_CRS_NAME = "cvslam nav frame: x east, y north, metres from the nav origin"
LOCAL_CRS_WKT = (
    f'LOCAL_CS["{LOCAL_CRS_NAME}",LOCAL_DATUM["cvslam nav frame origin",32767],'
    'UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Easting",EAST],AXIS["Northing",NORTH]]'
)
_FIT_SAMPLES = 7  # per side of the grid of points the UTM affine is fitted on


@dataclass(frozen=True, eq=False)
class MapPlacement:
    """Map coordinates (x, y) = M @ (east, north) + t of nav points; M (2, 2), t (2,) [m].
    `crs_wkt` the map's CRS (WKT), `crs_name` how to name it in messages (e.g.
    "EPSG:32632"), `max_fit_error_m` the largest distance between the affine and the exact
    mapping over the extent it was fitted on (0 for the local CRS)."""

    M: F64
    t: F64
    crs_wkt: str
    crs_name: str
    max_fit_error_m: float = 0.0

    def __post_init__(self) -> None:
        M, t = np.asarray(self.M, float), np.asarray(self.t, float)
        if M.shape != (2, 2) or t.shape != (2,):
            raise ValueError(f"MapPlacement: need M (2, 2), t (2,), got {M.shape}, {t.shape}")
        object.__setattr__(self, "M", M)
        object.__setattr__(self, "t", t)

    def map_xy(self, north_m: F64, east_m: F64) -> F64:
        """(..., 2) map coordinates of nav points."""
        en = np.stack(np.broadcast_arrays(np.asarray(east_m, float), np.asarray(north_m, float)))
        return np.moveaxis(np.tensordot(self.M, en, axes=1), 0, -1) + self.t

    def raster_transform(
        self, n_max: float, e_min: float, gsd_m: float
    ) -> tuple[float, float, float, float, float, float]:
        """(a, b, c, d, e, f) of a north-up nav raster whose top-left pixel corner is at
        (n_max, e_min): the map coordinates of pixel corner (col, row) are x = a col + b row
        + c, y = d col + e row + f (GDAL's and rasterio's `Affine` order and convention)."""
        (m00, m01), (m10, m11) = self.M
        c, f = self.map_xy(n_max, e_min)
        return (
            float(m00 * gsd_m),
            float(-m01 * gsd_m),
            float(c),
            float(m10 * gsd_m),
            float(-m11 * gsd_m),
            float(f),
        )


def local_placement() -> MapPlacement:
    """The local engineering map: x = east, y = north of the nav frame, in metres."""
    return MapPlacement(np.eye(2), np.zeros(2), LOCAL_CRS_WKT, "local (nav east/north, m)")


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """The EPSG code of the WGS 84 UTM zone of a point: the standard 6-degree zone of its
    longitude (no Norway or Svalbard exceptions), north (326zz) or south (327zz)."""
    zone = math.floor((lon_deg + 180.0) / 6.0) % 60 + 1
    return (32600 if lat_deg >= 0.0 else 32700) + zone


def nav_to_geodetic(lat_deg: float, lon_deg: float, alt_m: float) -> pyproj.Transformer:
    """PROJ's mapping of topocentric coordinates at the origin (true east, true north, up;
    metres) to longitude, latitude (degrees) and ellipsoidal height: the nav frame is the
    local tangent plane there, and `topocentric_en` turns nav (north, east) into it."""
    return pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +inv +proj=topocentric +ellps=WGS84 "
        f"+lat_0={lat_deg!r} +lon_0={lon_deg!r} +h_0={alt_m!r} "
        "+step +inv +proj=cart +ellps=WGS84 +step +proj=unitconvert +xy_in=rad +xy_out=deg"
    )


def topocentric_en(north_m: F64, east_m: F64, heading_deg: float) -> tuple[F64, F64]:
    """(true east, true north) [m] of nav (north, east): the nav axes turned by the heading."""
    h = math.radians(heading_deg)
    n, e = np.asarray(north_m, float), np.asarray(east_m, float)
    return n * math.sin(h) + e * math.cos(h), n * math.cos(h) - e * math.sin(h)


def utm_placement(
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    heading_deg: float,
    box_ne: tuple[float, float, float, float],
    up_m: float = 0.0,
) -> MapPlacement:
    """The UTM map of the nav frame anchored at the origin (module docstring), fitted over
    `box_ne` = (n_min, e_min, n_max, e_max) [m], the extent of the rasters it places, for
    points `up_m` above the origin (the rasters' ground: -z_nav)."""
    n_min, e_min, n_max, e_max = (float(x) for x in box_ne)
    nn, ee = np.meshgrid(
        np.linspace(n_min, n_max, _FIT_SAMPLES), np.linspace(e_min, e_max, _FIT_SAMPLES)
    )
    n, e = nn.ravel(), ee.ravel()
    epsg = utm_epsg(lat_deg, lon_deg)
    to_geo = nav_to_geodetic(lat_deg, lon_deg, alt_m)
    to_utm = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)
    lon, lat, _ = to_geo.transform(*topocentric_en(n, e, heading_deg), np.full_like(n, up_m))
    x, y = to_utm.transform(lon, lat)
    xy = np.c_[x, y]
    if not np.all(np.isfinite(xy)):  # a bug: every valid origin and nav point maps
        raise ValueError(f"nav box {box_ne} has no UTM coordinates from origin {lat_deg, lon_deg}")
    design = np.c_[e, n, np.ones_like(n)]
    # fit about the box's centre, so the offsets stay small next to the UTM coordinates
    centre = xy.mean(axis=0)
    coef, *_ = np.linalg.lstsq(design, xy - centre, rcond=None)
    M, t = coef[:2].T, coef[2] + centre
    error = float(np.max(np.linalg.norm(design @ coef + centre - xy, axis=1)))
    crs = pyproj.CRS.from_epsg(epsg)
    return MapPlacement(M, t, crs.to_wkt(), f"EPSG:{epsg} ({crs.name})", error)


def scale_bar_m(span_m: float, fraction: float = 0.25) -> float:
    """A round length (1, 2 or 5 x 10^k m) for the scale bar of a map `span_m` wide: the
    largest at most `fraction` of it."""
    if not (math.isfinite(span_m) and span_m > 0):
        raise ValueError(f"scale_bar_m: need a positive width, got {span_m}")
    target = span_m * fraction
    k = math.floor(math.log10(target))
    return max(s * 10.0**k for s in (1.0, 2.0, 5.0) if s * 10.0**k <= target * (1 + 1e-12))
