"""Files of `cvslam mosaic`: PNG images with an alpha channel, ESRI world files, the PNGs'
CRS as GDAL's PAM sidecar, GeoTIFFs, and the simulator's true ground raster (for checking a
mosaic).

World file (`.pgw` beside a `.png`): six lines A, D, B, E, C, F mapping pixel (col, row) to
map coordinates x = A col + B row + C, y = D col + E row + F, with (C, F) the centre of the
top-left pixel. The map is that of `geometry/georef.py`: by default the nav frame's east
(x) and north (y) in metres, A = gsd, E = -gsd, B = D = 0; in UTM (with `geo.origin`) a
rotated and scaled affine. The CRS goes beside the PNG in `<name>.png.aux.xml` (what GDAL
and QGIS read for formats that carry none) and into the GeoTIFF, whose pixels are the PNG's
(RGBA bands) and whose transform is the world file's.
"""

from __future__ import annotations

import html
from pathlib import Path

import cv2
import numpy as np
import rasterio
from numpy.typing import NDArray
from rasterio.crs import CRS
from rasterio.transform import Affine

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import atomic_file, write_bytes_atomic, write_text_atomic
from cvslam_cli.io.textfiles import read_text


def write_png_atomic(path: Path, image: NDArray[np.uint8], mask: NDArray[np.bool_] | None) -> None:
    """PNG of a grey or BGR image; with `mask`, BGRA with alpha 0 where the mask is False."""
    img = image if mask is None else _bgra(image, mask)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise CvslamError(f"{path}: could not encode the PNG image")
    write_bytes_atomic(path, buf.tobytes())


# (a, b, c, d, e, f): map x = a col + b row + c, y = d col + e row + f of pixel corners
RasterTransform = tuple[float, float, float, float, float, float]


def _bgra(image: NDArray[np.uint8], mask: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """The BGRA pixels `write_png_atomic` writes for `image` and `mask`."""
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
    return np.dstack([bgr, np.where(mask, 255, 0).astype(np.uint8)])


def world_file_values(transform: RasterTransform) -> tuple[float, ...]:
    """(A, D, B, E, C, F) of a raster `transform` (pixel corners): C, F the map
    coordinates of the centre of the top-left pixel."""
    a, b, c, d, e, f = transform
    return (a, d, b, e, c + 0.5 * (a + b), f + 0.5 * (d + e))


def write_world_file(path: Path, transform: RasterTransform) -> None:
    text = "".join(f"{v:.10f}\n" for v in world_file_values(transform))
    write_text_atomic(path, text, encoding="ascii")


def write_crs_sidecar(image_path: Path, crs_wkt: str) -> None:
    """`<image>.aux.xml`: GDAL's PAM file giving the CRS of an image with a world file (the
    axis order of both is x, y: east, north)."""
    text = (
        "<PAMDataset>\n"
        f'  <SRS dataAxisToSRSAxisMapping="1,2">{html.escape(crs_wkt)}</SRS>\n'
        "</PAMDataset>\n"
    )
    write_text_atomic(image_path.with_name(image_path.name + ".aux.xml"), text)


def write_geotiff_atomic(
    path: Path,
    image: NDArray[np.uint8],
    mask: NDArray[np.bool_],
    transform: RasterTransform,
    crs_wkt: str,
) -> None:
    """A GeoTIFF of the pixels `write_png_atomic` writes (RGBA bands, the alpha band 0
    where `mask` is False), with `transform` (pixel corners) and the CRS `crs_wkt`."""
    rgba = _bgra(image, mask)[..., [2, 1, 0, 3]]
    h, w = rgba.shape[:2]
    with (
        atomic_file(path) as tmp,
        rasterio.open(
            tmp,
            "w",
            driver="GTiff",
            width=w,
            height=h,
            count=4,
            dtype="uint8",
            crs=CRS.from_wkt(crs_wkt),
            transform=Affine(*transform),
            photometric="RGB",
            alpha="YES",  # the fourth band is the alpha channel: no-data where 0
            # deflate (every GeoTIFF reader has it), fast level with the horizontal
            # predictor: as small as the default level, 5x faster (BENCHMARKS.md, "Mosaic:
            # GeoTIFF")
            compress="deflate",
            zlevel=1,
            predictor=2,
            tiled=True,
        ) as ds,
    ):
        ds.write(np.moveaxis(rgba, -1, 0))


def read_world_file(path: Path) -> tuple[float, ...]:
    """The six values of a world file; CvslamError naming the file otherwise."""
    text = read_text(path, "a world file (6 numbers, one per line)")
    try:
        values = tuple(float(x) for x in text.split())
    except ValueError as exc:
        raise CvslamError(f"{path}: not a world file ({exc})") from None
    if len(values) != 6:
        raise CvslamError(f"{path}: a world file has 6 numbers, found {len(values)}")
    return values


def load_true_ground(path: Path) -> tuple[NDArray[np.uint8], tuple[float, float], float] | None:
    """(texture, origin (n0, e0) m, texels per metre) of the ground of a simulated world
    (`<run>/truth/world.npz`), or None when the file is absent."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            if "texture" in npz.files:  # terrain world
                tex, px = npz["texture"], float(npz["texture_px_per_m"])
            else:  # yard world
                tex, px = npz["ground_texture"], float(npz["ground_px_per_m"])
            origin = npz["origin_nav_m"]
    except (OSError, ValueError, KeyError) as exc:
        raise CvslamError(f"{path}: not a readable simulated world ({exc})") from None
    return np.asarray(tex), (float(origin[0]), float(origin[1])), px
