"""Files of `cvslam mosaic`: PNG images with an alpha channel, ESRI world files, and the
simulator's true ground raster (for checking a mosaic).

World file (`.pgw` beside a `.png`): six lines A, D, B, E, C, F mapping pixel (col, row) to
map coordinates x = A col + B row + C, y = D col + E row + F, with (C, F) the centre of the
top-left pixel. cvslam's mosaics are north-up in the nav frame: map x = nav y (east, m),
map y = nav x (north, m); A = gsd, E = -gsd, B = D = 0. A GIS (QGIS, GDAL) then places them in
metres; give the layer a local engineering CRS, the nav frame has no geodetic datum.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import write_bytes_atomic, write_text_atomic
from cvslam_cli.io.textfiles import read_text


def write_png_atomic(path: Path, image: NDArray[np.uint8], mask: NDArray[np.bool_] | None) -> None:
    """PNG of a grey or BGR image; with `mask`, BGRA with alpha 0 where the mask is False."""
    img = image
    if mask is not None:
        bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
        img = np.dstack([bgr, np.where(mask, 255, 0).astype(np.uint8)])
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise CvslamError(f"{path}: could not encode the PNG image")
    write_bytes_atomic(path, buf.tobytes())


def world_file_values(n_max: float, e_min: float, gsd_m: float) -> tuple[float, ...]:
    """(A, D, B, E, C, F) of a north-up raster whose top-left corner is at (n_max, e_min)."""
    return (gsd_m, 0.0, 0.0, -gsd_m, e_min + 0.5 * gsd_m, n_max - 0.5 * gsd_m)


def write_world_file(path: Path, n_max: float, e_min: float, gsd_m: float) -> None:
    text = "".join(f"{v:.10f}\n" for v in world_file_values(n_max, e_min, gsd_m))
    write_text_atomic(path, text, encoding="ascii")


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
