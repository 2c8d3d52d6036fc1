"""The yard world: geometry of the ray-cast views against `project_points`, stereo
disparity, scene content, free space, determinism and spec checks."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.geometry.camera import CameraModel, translation_T
from cvslam_cli.geometry.projection import project_points
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, invert_T, make_T
from cvslam_cli.sim.render import RenderResult
from cvslam_cli.sim.yard import (
    Yard,
    YardSpec,
    camera_rays,
    make_yard,
    render_yard_view,
)

W, H = 752, 480
K = np.array([[450.0, 0.0, 375.5], [0.0, 452.0, 239.5], [0.0, 0.0, 1.0]])
D_EUROC_LIKE = np.array([-0.25, 0.07, 2e-4, 2e-5, 0.0])
# camera optical axes (x right, y down, z forward) in the robot's FRD body frame
R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
CAM_HEIGHT_M = 0.5


def _cam(distorted: bool = False) -> CameraModel:
    if distorted:
        return CameraModel(W, H, K, D_EUROC_LIKE, "plumb_bob")
    return CameraModel(W, H, K, P=np.hstack([K, np.zeros((3, 1))]))


def _pose(n: float, e: float, yaw: float, tilt_rad: float = 0.1) -> np.ndarray:
    """T_nav_cam of a forward camera at CAM_HEIGHT_M looking along `yaw`, tilted down."""
    return make_T(euler_zyx_to_matrix(0.0, -tilt_rad, yaw) @ R_BODY_CAM, [n, e, -CAM_HEIGHT_M])


@pytest.fixture(scope="module")
def yard() -> Yard:
    return make_yard(YardSpec(), np.random.default_rng(7))


def _free_poses(yard: Yard, rng: np.random.Generator, k: int) -> list[np.ndarray]:
    poses: list[np.ndarray] = []
    while len(poses) < k:
        n, e = rng.uniform(-18, 18, 2)
        if yard.free_space_ok(n, e, 1.5):
            poses.append(_pose(n, e, rng.uniform(-np.pi, np.pi), rng.uniform(0.0, 0.15)))
    return poses


def _surface_samples(
    yard: Yard, T_nav_cam: np.ndarray, rng: np.random.Generator, n_pts: int
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) nav points on the ground (within 12 m, ahead) and on the walls, and the
    surface index of each (-1 ground, i wall i)."""
    o, fwd = T_nav_cam[:3, 3], T_nav_cam[:3, 2]
    n_ground = n_pts // 2
    ang = np.arctan2(fwd[1], fwd[0]) + rng.uniform(-0.8, 0.8, n_ground)
    r = rng.uniform(0.8, 12.0, n_ground)
    ground = np.column_stack([o[0] + r * np.cos(ang), o[1] + r * np.sin(ang), np.zeros(n_ground)])
    wall_ids = rng.integers(0, len(yard.walls), n_pts - n_ground)
    pts = [ground]
    for i in range(len(yard.walls)):
        k = int(np.sum(wall_ids == i))
        w = yard.walls[i]
        pts.append(w.point_nav_m(rng.uniform(0, w.length_m, k), rng.uniform(0, w.height_m, k)))
    ids = np.concatenate([np.full(n_ground, -1), np.sort(wall_ids)])
    return np.concatenate(pts), ids


def _ray_plane_hit(
    yard: Yard, T_nav_cam: np.ndarray, ray_cam: np.ndarray, surface: np.ndarray
) -> np.ndarray:
    """(N,) ray parameter (= camera depth) where each camera ray (x/z, y/z, 1) meets the plane
    of its surface (ground z = 0, or the vertical plane of wall i)."""
    R, o = T_nav_cam[:3, :3], T_nav_cam[:3, 3]
    d = ray_cam @ R.T
    t = -o[2] / d[:, 2]
    for k in np.flatnonzero(surface >= 0):
        w = yard.walls[surface[k]]
        m = np.array([-w.direction_ne[1], w.direction_ne[0]])
        t[k] = m @ (w.p0_ne - o[:2]) / (m @ d[k, :2])
    return t


def _texture_at(yard: Yard, p_nav: np.ndarray, surface: np.ndarray) -> np.ndarray:
    out = np.asarray(yard.ground_texture_at(p_nav[:, 0], p_nav[:, 1]), dtype=float)
    for i in np.unique(surface[surface >= 0]):
        sel = surface == i
        w = yard.walls[i]
        s = (p_nav[sel, :2] - w.p0_ne) @ w.direction_ne
        out[sel] = yard.wall_texture_at(int(i), s, -p_nav[sel, 2])
    return out


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    top = img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu
    bot = img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu
    return top * (1 - fv) + bot * fv


def _interior(
    yard: Yard,
    view: RenderResult,
    T_nav_cam: np.ndarray,
    rays: np.ndarray,
    uv: np.ndarray,
    surface: np.ndarray,
) -> np.ndarray:
    """(N,) whether all four pixels around each sub-pixel position `uv` see the given
    surface (their rendered depth is where their ray meets that surface's plane)."""
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = np.ones(len(uv), bool)
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        t = _ray_plane_hit(yard, T_nav_cam, rays[v0 + dv, u0 + du], surface)
        ok &= np.abs(view.depth_m[v0 + dv, u0 + du] - t) < 1e-4 * t
    return ok


def _on_surface(yard: Yard, p_nav: np.ndarray, surface: np.ndarray) -> np.ndarray:
    n0, e0 = yard.spec.origin_nav_m
    sn, se = yard.spec.size_m
    ok = (p_nav[:, 0] > n0) & (p_nav[:, 0] < n0 + sn) & (p_nav[:, 1] > e0)
    ok &= p_nav[:, 1] < e0 + se
    for k in np.flatnonzero(surface >= 0):
        w = yard.walls[surface[k]]
        s = (p_nav[k, :2] - w.p0_ne) @ w.direction_ne
        ok[k] = 1e-3 < s < w.length_m - 1e-3 and 1e-3 < -p_nav[k, 2] < w.height_m - 1e-3
    return ok


@pytest.mark.parametrize("distorted", [False, True])
def test_rendered_depth_and_radiance_match_projected_surface_points(yard, distorted):
    cam = _cam(distorted)
    rays = camera_rays(cam)
    rng = np.random.default_rng(3)
    n_checked = n_visible = n_interior = 0
    rad_resid: list[np.ndarray] = []
    for T in _free_poses(yard, rng, 4):
        view = render_yard_view(yard, cam, T, rays=rays)
        p_nav, surface = _surface_samples(yard, T, rng, 1000)
        p_cam = (p_nav - T[:3, 3]) @ T[:3, :3]
        uv, front = project_points(cam, p_cam)
        inside = front & (uv[:, 0] >= 1) & (uv[:, 0] <= W - 2) & (uv[:, 1] >= 1)
        inside &= uv[:, 1] <= H - 2
        uv, p_cam, surface = uv[inside], p_cam[inside], surface[inside]
        # Q: where the ray of the nearest pixel centre meets the sampled point's surface.
        ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        ray = rays[vi, ui]
        t_q = _ray_plane_hit(yard, T, ray, surface)
        q_cam = ray * t_q[:, None]
        q_nav = q_cam @ T[:3, :3].T + T[:3, 3]
        keep = _on_surface(yard, q_nav, surface) & (t_q > 0)
        uv_q, _ = project_points(cam, q_cam[keep])
        np.testing.assert_allclose(uv_q, np.column_stack([ui, vi])[keep], atol=1e-5)
        depth_px = view.depth_m[vi, ui].astype(float)
        # the surface is never missed: what the pixel sees is at Q or in front of it ...
        assert view.valid[vi, ui][keep].all()
        assert np.all(depth_px[keep] <= t_q[keep] * (1 + 1e-5))
        # ... and, unless something occludes Q, exactly at Q
        visible = keep & (depth_px >= t_q * (1 - 1e-5))
        n_checked += int(keep.sum())
        n_visible += int(visible.sum())
        rad_resid.append(
            view.radiance[vi, ui][visible] - _texture_at(yard, q_nav[visible], surface[visible])
        )
        # sub-pixel: inverse depth interpolated at the projected point (linear on a plane)
        interior = _interior(yard, view, T, rays, uv, surface)
        inv = 1.0 / view.depth_m.astype(float)
        n_interior += int(interior.sum())
        inv_at = _bilinear(inv, uv[interior])
        np.testing.assert_allclose(1.0 / inv_at, p_cam[interior, 2], rtol=1e-3)
    assert n_checked > 1000
    assert n_visible > 0.6 * n_checked, (n_visible, n_checked)
    assert n_interior > 0.5 * n_checked
    resid = np.abs(np.concatenate(rad_resid))
    # bilinear texture lookup at Q (OpenCV's fixed-point remap weights allow ~1/64 texel);
    # a texture shifted by 0.2 texel along the walls already gives a mean of ~1.4e-4
    assert resid.mean() < 3e-5 and resid.max() < 0.02, (resid.mean(), resid.max())


def test_stereo_disparity_and_right_view_depth(yard):
    b = 0.12
    left = _cam()
    P_right = left.P.copy()
    P_right[0, 3] = -left.fx * b
    right = CameraModel(W, H, K, P=P_right, T_body_cam=translation_T(b))
    rng = np.random.default_rng(11)
    n_interior = 0
    for T_left in _free_poses(yard, rng, 3):
        T_right = T_left @ translation_T(b)
        view_r = render_yard_view(yard, right, T_right)
        p_nav, surface = _surface_samples(yard, T_left, rng, 600)
        p_l = (p_nav - T_left[:3, 3]) @ T_left[:3, :3]
        p_r = (np.c_[p_nav, np.ones(len(p_nav))] @ invert_T(T_right).T)[:, :3]
        uv_l, front_l = project_points(left, p_l)
        uv_r, front_r = project_points(right, p_r)
        ok = front_l & front_r & (uv_r[:, 0] >= 1) & (uv_r[:, 0] <= W - 2)
        ok &= (uv_r[:, 1] >= 1) & (uv_r[:, 1] <= H - 2)
        z = p_l[ok, 2]
        np.testing.assert_allclose(p_r[ok, 2], z, rtol=1e-12)
        np.testing.assert_allclose(uv_l[ok, 0] - uv_r[ok, 0], left.fx * b / z, rtol=1e-9)
        np.testing.assert_allclose(uv_l[ok, 1], uv_r[ok, 1], atol=1e-9)
        inv = 1.0 / view_r.depth_m.astype(float)
        uv = uv_r[ok]
        interior = _interior(yard, view_r, T_right, camera_rays(right), uv, surface[ok])
        n_interior += int(interior.sum())
        np.testing.assert_allclose(1.0 / _bilinear(inv, uv[interior]), z[interior], rtol=1e-3)
    assert n_interior > 300


def test_views_show_walls_ground_and_sky_only_across_the_yard(yard):
    cam = _cam()
    n0, e0 = yard.spec.origin_nav_m
    sn, _ = yard.spec.size_m
    # 3 m from the west perimeter wall, facing it: the wall fills the top, no sky
    n_mid = n0 + sn / 2
    candidates = [(n, e0 + 3.0) for n in np.linspace(n0 + 5, n0 + sn - 5, 15)]
    n, e = min(candidates, key=lambda p: abs(p[0] - n_mid) + 100 * (not yard.free_space_ok(*p, 2)))
    close = render_yard_view(yard, cam, _pose(n, e, -np.pi / 2), want_points=True)
    assert close.valid.all()
    z = close.p_nav_m[..., 2]
    ground = np.abs(z) < 1e-3
    assert 0.1 < ground.mean() < 0.9
    assert (z < -0.05).mean() > 0.1
    np.testing.assert_allclose(close.p_nav_m[..., 1][~ground], e0, atol=1e-3)
    # across the yard: sky above the walls, smooth and without depth
    far = render_yard_view(yard, cam, _pose(n0 + 2, e0 + 2, np.pi / 4, 0.0))
    sky = ~far.valid
    assert 0.05 < sky.mean() < 0.8
    assert np.isnan(far.depth_m[sky]).all() and np.isfinite(far.depth_m[~sky]).all()
    assert far.radiance.dtype == np.float32 and far.radiance.shape == (H, W)
    assert far.radiance.min() >= 0.0 and far.radiance.max() <= 1.0


def test_free_space_rejects_walls_obstacles_and_outside(yard):
    n0, e0 = yard.spec.origin_nav_m
    sn, se = yard.spec.size_m
    boxes = [p for p in yard.obstacles_ne if len(p) == 4]
    panels = [p for p in yard.obstacles_ne if len(p) == 2]
    assert boxes and panels
    for box in boxes:
        c = box.mean(axis=0)
        assert not yard.free_space_ok(c[0], c[1], 0.0)
    for panel in panels:
        c = panel.mean(axis=0)
        assert not yard.free_space_ok(c[0], c[1], 0.2)
    assert not yard.free_space_ok(n0 - 1.0, e0 + 5.0)
    assert not yard.free_space_ok(n0 + 0.3, e0 + 5.0, 0.5)
    nn, ee = np.meshgrid(np.linspace(n0, n0 + sn, 41), np.linspace(e0, e0 + se, 41))
    ok = yard.free_space_ok(nn, ee, 0.5)
    assert ok.shape == nn.shape and 0.5 < ok.mean() < 0.95


def test_wall_texture_coordinates(yard):
    w = yard.walls[5]
    rows, cols = np.array([0, 3, w.texture.shape[0] - 1]), np.array([0, 17, 40])
    s = (cols + 0.5) / w.px_per_m
    h = w.height_m - (rows + 0.5) / w.px_per_m
    np.testing.assert_allclose(yard.wall_texture_at(5, s, h), w.texture[rows, cols] / 255.0, 1e-6)
    g = yard.ground_texture
    n0, e0 = yard.spec.origin_nav_m
    ppm = yard.spec.ground_px_per_m
    got = yard.ground_texture_at(n0 + (np.array([2, 9]) + 0.5) / ppm, e0 + 10.5 / ppm)
    np.testing.assert_allclose(got, g[[2, 9], 10] / 255.0, atol=1e-6)


def test_same_seed_same_yard_and_images():
    spec = YardSpec(size_m=(20.0, 16.0), origin_nav_m=(0.0, 0.0), n_obstacles=3)
    a, b = (make_yard(spec, np.random.default_rng(5)) for _ in range(2))
    c = make_yard(spec, np.random.default_rng(6))
    assert len(a.walls) == len(b.walls)
    assert np.array_equal(a.ground_texture, b.ground_texture)
    for wa, wb in zip(a.walls, b.walls, strict=True):
        assert np.array_equal(wa.p0_ne, wb.p0_ne) and np.array_equal(wa.p1_ne, wb.p1_ne)
        assert np.array_equal(wa.texture, wb.texture) and wa.height_m == wb.height_m
    assert not np.array_equal(a.ground_texture, c.ground_texture)
    T = _pose(3.0, 3.0, 0.6)
    cam = _cam(distorted=True)
    ra, rb = render_yard_view(a, cam, T), render_yard_view(b, cam, T)
    assert np.array_equal(ra.radiance, rb.radiance)
    assert np.array_equal(ra.depth_m, rb.depth_m, equal_nan=True)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"size_m": (0.0, 40.0)}, "size_m"),
        ({"wall_height_m": -1.0}, "wall_height_m"),
        ({"n_obstacles": -2}, "n_obstacles"),
        ({"ground_px_per_m": 1000.0}, "ground_px_per_m"),
        ({"size_m": (8.0, 8.0), "n_obstacles": 20}, "cannot place 20 obstacles"),
        ({"size_m": (4.0, 4.0), "n_obstacles": 1}, "no room for obstacles"),
    ],
)
def test_impossible_specs_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_yard(YardSpec(**kwargs), np.random.default_rng(0))


def test_render_rejects_bad_inputs(yard):
    cam = _cam()
    with pytest.raises(ValueError, match="4x4"):
        render_yard_view(yard, cam, np.eye(3))
    with pytest.raises(ValueError, match="rays"):
        render_yard_view(yard, cam, _pose(0, 0, 0), rays=np.zeros((10, 10, 3)))
