from __future__ import annotations

import cv2
import numpy as np
import pytest

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.projection import pixel_rays, project_points, undistort_pixels

K = np.array([[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1.0]])


def _cam(model: str, D: list[float]) -> CameraModel:
    return CameraModel(width=752, height=480, K=K, D=np.array(D), distortion_model=model)


@pytest.mark.parametrize(
    "model, D",
    [
        ("plumb_bob", [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]),
        ("equidistant", [0.01, -0.005, 0.001, 0.0]),
        ("none", []),
    ],
)
def test_projection_matches_opencv_and_inverts(model, D):
    cam = _cam(model, D)
    rng = np.random.default_rng(0)
    p = np.column_stack(
        [rng.uniform(-1.5, 1.5, 500), rng.uniform(-1, 1, 500), rng.uniform(2, 5, 500)]
    )
    uv, front = project_points(cam, p)
    assert front.all()
    if model == "equidistant":
        ref, _ = cv2.fisheye.projectPoints(
            p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.array(D)
        )
    else:
        ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, np.array(D) if D else None)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    inside = (uv[:, 0] > 0) & (uv[:, 0] < 751) & (uv[:, 1] > 0) & (uv[:, 1] < 479)
    xy = undistort_pixels(cam, uv[inside])
    np.testing.assert_allclose(xy, p[inside, :2] / p[inside, 2:3], atol=1e-7)


def test_pixel_rays_reproject_to_their_pixels():
    cam = _cam("plumb_bob", [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
    rays = pixel_rays(cam)
    assert rays.shape == (480, 752, 3)
    uv, _ = project_points(cam, rays[::7, ::11].reshape(-1, 3))
    vv, uu = np.mgrid[0:480:7, 0:752:11]
    np.testing.assert_allclose(uv, np.column_stack([uu.ravel(), vv.ravel()]), atol=1e-6)


def test_points_behind_are_flagged():
    uv, front = project_points(_cam("none", []), np.array([[0, 0, -1.0], [0, 0, 1.0]]))
    assert front.tolist() == [False, True] and np.isnan(uv[0]).all()
