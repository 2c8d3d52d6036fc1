"""Mosaic files: world files placing pixel centres, PNG with alpha, bad world files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.mosaic_files import read_world_file, write_png_atomic, write_world_file


def test_world_file_places_pixel_centres_in_east_north(tmp_path):
    path = tmp_path / "m.pgw"
    write_world_file(path, n_max=120.0, e_min=-40.0, gsd_m=0.25)
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
