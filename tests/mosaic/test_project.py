"""Projection of camera images onto the ground: canvas grid arithmetic, footprints, the
inverse warp against an analytically rendered view, forward-looking cameras."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.projection import undistort_pixels
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.mosaic.ground import GroundModel
from cvslam_cli.mosaic.project import (
    CanvasGrid,
    ViewLimits,
    footprint_box,
    image_gsd_m,
    warp_to_canvas,
)


def flat_ground(z_nav_m: float = 0.0) -> GroundModel:
    return GroundModel(
        global_abc=np.array([z_nav_m, 0.0, 0.0]),
        origin_ne=np.zeros(2),
        region_m=50.0,
        region_abc=np.full((1, 1, 3), [z_nav_m, 0.0, 0.0]),
        local=np.zeros((1, 1), bool),
        inliers=0,
        points=0,
        residual_rms_m=0.0,
    )


def texture(n, e):
    return 128.0 + 90.0 * np.sin(n / 2.3) * np.cos(e / 3.1)


def camera(distorted: bool) -> CameraModel:
    K = np.array([[420.0, 0, 319.5], [0, 420.0, 239.5], [0, 0, 1]])
    if distorted:
        return CameraModel(640, 480, K, np.array([-0.18, 0.05, 0.001, -0.0005, 0.0]), "plumb_bob")
    return CameraModel(640, 480, K)


def render(cam: CameraModel, T_nav_cam: np.ndarray, z_ground: float, sky: float = 255.0):
    """The view of the textured plane z = z_ground (NED), analytically: each pixel's ray
    (lens distortion undone) hits the plane; above the horizon: `sky`."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    xy = undistort_pixels(cam, np.c_[u.ravel(), v.ravel()])
    d = np.c_[xy, np.ones(len(xy))] @ T_nav_cam[:3, :3].T
    c = T_nav_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (z_ground - c[2]) / d[:, 2]
    hit = c + s[:, None] * d
    img = np.where(s > 0, texture(hit[:, 0], hit[:, 1]), sky)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8).reshape(cam.height, cam.width)


def pose(p, roll, pitch, yaw, R_body_cam):
    T = np.eye(4)
    T[:3, :3] = euler_zyx_to_matrix(roll, pitch, yaw) @ R_body_cam
    T[:3, 3] = p
    return T


# camera z (optical axis) = body z (down), camera x = body y (east when level), y = -body x
R_DOWN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
# camera z = body x (forward), x = body y (right), y = body z (down)
R_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def test_canvas_grid_pixels_rois_and_sub_grids():
    g = CanvasGrid.covering(np.array([-10.3, 5.1, 20.2, 40.0]), 0.5)
    assert g.n_max == 20.5 and g.e_min == 5.0
    box = g.box_ne()
    assert box[0] <= -10.3 and box[3] >= 40.0
    r, c = g.pixel_of(np.array([g.n_max - 0.25]), np.array([g.e_min + 0.25]))
    assert r[0] == pytest.approx(0.0) and c[0] == pytest.approx(0.0)
    roi = g.roi_of(np.array([0.0, 10.0, 5.0, 12.0]))
    sub = g.sub(roi)
    # the sub-grid's pixel centres are the parent's, shifted by the ROI corner
    r1, c1 = g.pixel_of(np.array([2.3]), np.array([11.1]))
    r2, c2 = sub.pixel_of(np.array([2.3]), np.array([11.1]))
    assert r1[0] - r2[0] == pytest.approx(roi[0]) and c1[0] - c2[0] == pytest.approx(roi[1])
    assert g.roi_of(np.array([100.0, 100.0, 110.0, 110.0])) is None


@pytest.mark.parametrize("distorted", [False, True], ids=["pinhole", "plumb_bob"])
def test_warp_reproduces_the_ground_under_a_tilted_downward_camera(distorted):
    cam = camera(distorted)
    T = pose([10.0, -5.0, -60.0], 0.08, -0.05, 0.6, R_DOWN)
    img = render(cam, T, z_ground=2.0)
    ground = flat_ground(2.0)
    limits = ViewLimits(max_range_m=1000.0, min_depression_deg=5.0, border_px=2)
    box = footprint_box(cam, T, ground, limits)
    gsd = image_gsd_m(cam, T, ground, limits)
    assert 0.13 < gsd < 0.17  # ~62 m / 420 px
    grid = CanvasGrid.covering(box, 0.15)
    roi = (0, 0, *grid.shape)
    out, mask = warp_to_canvas(img, cam, T, ground, grid, roi, limits)
    valid = mask > 0
    # the footprint box holds the whole view: nothing valid on the canvas border
    assert not valid[0].any() and not valid[-1].any()
    assert not valid[:, 0].any() and not valid[:, -1].any()
    assert valid.mean() > 0.4
    rows, cols = np.nonzero(valid)
    n = grid.n_max - (rows + 0.5) * grid.gsd_m
    e = grid.e_min + (cols + 0.5) * grid.gsd_m
    err = np.abs(out[valid].astype(float) - texture(n, e))
    assert np.median(err) < 1.5
    assert np.percentile(err, 99) < 8.0


def test_coarse_canvas_reduces_the_image_first():
    """At 4x the image's ground resolution the warped image is the smoothed texture, not an
    aliased sampling of it."""
    cam = camera(False)
    T = pose([0.0, 0.0, -60.0], 0.0, 0.0, 0.0, R_DOWN)
    fine_tex = lambda n, e: 128 + 100 * np.sin(2 * np.pi * n / 0.55)  # noqa: E731
    v, u = np.mgrid[0:480, 0:640].astype(float)
    # nadir view: n = -(v - cy) * 60 / f ... the exact rays as in render()
    xy = undistort_pixels(cam, np.c_[u.ravel(), v.ravel()])
    d = np.c_[xy, np.ones(len(xy))] @ T[:3, :3].T
    s = 60.0 / d[:, 2]
    hit = T[:3, 3] + s[:, None] * d
    img = np.clip(fine_tex(hit[:, 0], hit[:, 1]), 0, 255).astype(np.uint8).reshape(480, 640)
    ground = flat_ground(0.0)
    limits = ViewLimits(1000.0, 5.0, 2)
    grid = CanvasGrid.covering(footprint_box(cam, T, ground, limits), 0.6)
    out, mask = warp_to_canvas(img, cam, T, ground, grid, (0, 0, *grid.shape), limits)
    # a 0.55 m stripe pattern at 0.6 m/px: averaged away (aliasing would leave stripes)
    assert np.std(out[mask > 0]) < 25


def test_forward_camera_keeps_only_the_ground_below_the_horizon_within_range():
    cam = camera(False)
    T = pose([0.0, 0.0, -1.0], 0.0, 0.0, 0.3, R_FORWARD)  # 1 m above z = 0, yaw 0.3
    img = render(cam, T, z_ground=0.0, sky=255.0)
    assert (img == 255).mean() > 0.3  # the sky is in the image
    ground = flat_ground(0.0)
    limits = ViewLimits(max_range_m=20.0, min_depression_deg=5.0, border_px=2)
    box = footprint_box(cam, T, ground, limits)
    assert box is not None
    grid = CanvasGrid.covering(box, 0.05)
    out, mask = warp_to_canvas(img, cam, T, ground, grid, (0, 0, *grid.shape), limits)
    valid = mask > 0
    assert valid.any()
    assert (out[valid] < 250).all()  # no sky on the ground
    rows, cols = np.nonzero(valid)
    n = grid.n_max - (rows + 0.5) * grid.gsd_m
    e = grid.e_min + (cols + 0.5) * grid.gsd_m
    horiz = np.hypot(n, e)
    assert horiz.max() <= 20.0 + 1e-6
    # seen at least 5 degrees below the horizon: within 1 / tan(5 deg) = 11.4 m
    assert horiz.max() <= 1.0 / np.tan(np.radians(5.0)) + 0.1
    # in front of the camera (heading 0.3 rad)
    fwd = n * np.cos(0.3) + e * np.sin(0.3)
    assert (fwd > 0).all()
    err = np.abs(out[valid].astype(float) - texture(n, e))
    assert np.median(err) < 3.0
