"""`make bench`: the cost of the mosaics' GeoTIFFs (issue 19) against their PNGs.

A 16 Mpx (4000 x 4000) grey mosaic, the size `mosaic.auto_max_mpx` allows, textured like
a ground image (seeded noise blurred by a 3 px Gaussian) with 1/8 of it no-data, written by
`write_png_atomic` (the baseline, same run) and by `write_geotiff_atomic` (RGBA, deflate
level 1 with the horizontal predictor), and, for comparison, as the same GeoTIFF with
GDAL's default deflate level (6) and no predictor. Printed: seconds (best of 3) and size,
as ratios to the PNG. Asserted (not time): the chosen GeoTIFF is at most 10 % larger than
the default-level one and smaller than the PNG, and holds the same pixels.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import rasterio
from rasterio.transform import Affine

from cvslam_cli.geometry.georef import local_placement
from cvslam_cli.io.mosaic_files import write_geotiff_atomic, write_png_atomic

SIZE_PX = 4000
REPEATS = 3


def _best(fn) -> float:
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def test_geotiff_write_against_png(tmp_path: Path) -> None:
    rng = np.random.default_rng(19)
    image = cv2.GaussianBlur(rng.integers(0, 256, (SIZE_PX, SIZE_PX), dtype=np.uint8), (0, 0), 3)
    mask = np.ones(image.shape, bool)
    mask[:, : SIZE_PX // 8] = False
    placement = local_placement()
    transform = placement.raster_transform(0.0, 0.0, 0.2)
    png, tif, default = tmp_path / "m.png", tmp_path / "m.tif", tmp_path / "default.tif"
    rgba = np.stack([image, image, image, np.where(mask, 255, 0).astype(np.uint8)])

    def default_level() -> None:
        with rasterio.open(
            default, "w", driver="GTiff", width=SIZE_PX, height=SIZE_PX, count=4,
            dtype="uint8", crs=placement.crs_wkt, transform=Affine(*transform),
            photometric="RGB", alpha="YES", compress="deflate", tiled=True,
        ) as ds:  # fmt: skip
            ds.write(rgba)

    t_png = _best(lambda: write_png_atomic(png, image, mask))
    t_tif = _best(lambda: write_geotiff_atomic(tif, image, mask, transform, placement.crs_wkt))
    t_default = _best(default_level)
    sizes = {p.name: p.stat().st_size for p in (png, tif, default)}
    print(
        f"\nGeoTIFF of a {SIZE_PX}x{SIZE_PX} grey mosaic (best of {REPEATS}):\n"
        f"  PNG (baseline)            {t_png:6.2f} s  {sizes['m.png'] / 2**20:6.1f} MiB\n"
        f"  GeoTIFF deflate 1 + pred. {t_tif:6.2f} s  {sizes['m.tif'] / 2**20:6.1f} MiB"
        f"  ({t_tif / t_png:.2f}x the PNG's time, {sizes['m.tif'] / sizes['m.png']:.2f}x size)\n"
        f"  GeoTIFF deflate 6         {t_default:6.2f} s  {sizes['default.tif'] / 2**20:6.1f} MiB"
        f"  ({t_default / t_png:.2f}x, {sizes['default.tif'] / sizes['m.png']:.2f}x)"
    )
    assert sizes["m.tif"] <= 1.1 * sizes["default.tif"] and sizes["m.tif"] < sizes["m.png"]
    with rasterio.open(tif) as ds:
        assert np.array_equal(ds.read(), rgba)
