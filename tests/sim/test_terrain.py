"""The UAV terrain world and its ray-cast stereo views: relief, regions, and the geometry of
the rendered images against the independent forward model (`project_points`)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.projection import pixel_rays, project_points
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, invert_T, make_T
from cvslam_cli.sim.terrain import (
    Terrain,
    TerrainSpec,
    make_terrain,
    render_terrain_view,
)

W, H, F = 752, 480, 450.0
K = np.array([[F, 0.0, 376.0], [0.0, F, 240.0], [0.0, 0.0, 1.0]])
D_LENS = np.array([-0.25, 0.07, 0.0, 0.0, 0.0])
BASELINE_M = 0.6
# camera x -> body right, y -> body backwards, z -> body down: a nadir camera, image top north
R_BODY_CAM = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Rig:
    left: CameraModel
    right: CameraModel
    T_left_right: np.ndarray
    rays_left: np.ndarray
    rays_right: np.ndarray


def _camera(D: np.ndarray | None) -> CameraModel:
    if D is None:
        return CameraModel(W, H, K.copy())
    return CameraModel(W, H, K.copy(), D=D.copy(), distortion_model="plumb_bob")


def _rotation_deg(axis: np.ndarray, deg: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(deg))
    return R


@pytest.fixture(scope="module")
def terrain() -> Terrain:
    return make_terrain(TerrainSpec(), np.random.default_rng(7))


@pytest.fixture(scope="module")
def rigs() -> dict[str, Rig]:
    plain = _camera(None)
    distorted = _camera(D_LENS)
    rays_plain, rays_distorted = pixel_rays(plain), pixel_rays(distorted)
    T_rect = make_T(np.eye(3), np.array([BASELINE_M, 0.0, 0.0]))
    T_skew = make_T(_rotation_deg(np.array([0.3, 1.0, 0.2]), 1.0), np.array([BASELINE_M, 0.01, 0]))
    return {
        "rectified": Rig(plain, plain, T_rect, rays_plain, rays_plain),
        "distorted": Rig(distorted, distorted, T_skew, rays_distorted, rays_distorted),
    }


def _pose(terrain: Terrain, n: float, e: float, agl_m: float, rpy_deg: tuple) -> np.ndarray:
    roll, pitch, yaw = np.radians(rpy_deg)
    C_nav_body = euler_zyx_to_matrix(roll, pitch, yaw)
    z = -(float(terrain.elevation_at(n, e)) + agl_m)
    return make_T(C_nav_body @ R_BODY_CAM, np.array([n, e, z]))


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Exact float64 bilinear sample of img at (u, v) = (col, row)."""
    u, v = uv[:, 0], uv[:, 1]
    j, i = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - j, v - i
    im = img.astype(np.float64)
    top = im[i, j] * (1 - fu) + im[i, j + 1] * fu
    bottom = im[i + 1, j] * (1 - fu) + im[i + 1, j + 1] * fu
    return top * (1 - fv) + bottom * fv


def _visible_points(
    terrain: Terrain, cam: CameraModel, T_nav_cam: np.ndarray, n_c: float, e_c: float, count: int
):
    """`count` random surface points near (n_c, e_c) that project inside the image."""
    rng = np.random.default_rng(11)
    n = n_c + rng.uniform(-90, 90, 6 * count)
    e = e_c + rng.uniform(-90, 90, 6 * count)
    p_nav = terrain.surface_nav(n, e)
    p_cam = (invert_T(T_nav_cam) @ np.column_stack([p_nav, np.ones(len(p_nav))]).T).T[:, :3]
    uv, front = project_points(cam, p_cam)
    inside = front & (uv[:, 0] > 2) & (uv[:, 0] < W - 3) & (uv[:, 1] > 2) & (uv[:, 1] < H - 3)
    keep = np.flatnonzero(inside)[:count]
    assert keep.size == count
    return n[keep], e[keep], p_cam[keep], uv[keep]


def _ortho_patch_shift(
    terrain: Terrain,
    cam: CameraModel,
    T_nav_cam: np.ndarray,
    radiance: np.ndarray,
    n_c: float,
    e_c: float,
    inject_m: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Misregistration (north, east), in texels, of the rendered image against the texture.

    The rendered image is resampled onto a 64 x 64 texel grid around (n_c, e_c) through the
    forward geometry only (surface point -> `project_points`), and the sub-texel shift d that
    best explains it as texture(x + d) is found by Lucas-Kanade (Gauss-Newton on the SSD).
    `inject_m` shifts the texture side to check that the measure sees a known shift."""
    step = 1.0 / terrain.spec.texture_px_per_m
    g = (np.arange(64) - 31.5) * step
    nn, ee = (a.ravel() for a in np.meshgrid(n_c + g, e_c + g, indexing="ij"))
    p_nav = terrain.surface_nav(nn, ee)
    p_cam = (invert_T(T_nav_cam) @ np.column_stack([p_nav, np.ones(len(p_nav))]).T).T[:, :3]
    uv, _ = project_points(cam, p_cam)
    rendered = _bilinear(radiance, uv)
    d, h = np.zeros(2), 0.5 * step
    for _ in range(10):
        n1, e1 = nn + inject_m[0] + d[0], ee + inject_m[1] + d[1]
        tex = terrain.texture_at(n1, e1)
        J = np.column_stack(
            [
                terrain.texture_at(n1 + h, e1) - terrain.texture_at(n1 - h, e1),
                terrain.texture_at(n1, e1 + h) - terrain.texture_at(n1, e1 - h),
            ]
        ) / (2 * h)
        dd = np.linalg.lstsq(J, rendered - tex, rcond=None)[0]
        d += dd
        if np.abs(dd).max() < 1e-4 * step:
            break
    return d / step


def _busy_spots(terrain: Terrain, n_c: float, e_c: float, count: int) -> list[tuple[float, float]]:
    """Centres of busy 16 m patches within 30 m of (n_c, e_c) (well inside a view from 100 m),
    highest contrast first."""
    spots = []
    for dn in np.arange(-30, 31, 10.0):
        for de in np.arange(-30, 31, 10.0):
            n, e = n_c + dn, e_c + de
            g = np.linspace(-8, 8, 33)
            nn, ee = np.meshgrid(n + g, e + g, indexing="ij")
            contrast = float(np.std(terrain.texture_at(nn, ee)))
            spots.append((contrast, n, e))
    spots.sort(reverse=True)
    return [(n, e) for _, n, e in spots[:count]]


# -- the world ----------------------------------------------------------------------------------


def test_relief_and_regions(terrain: Terrain):
    spec = terrain.spec
    E = terrain.elevation_m
    assert E.shape == (401, 401) and terrain.texture.shape == (3200, 3200)
    assert np.ptp(E) == pytest.approx(spec.relief_m, rel=1e-9)
    assert 0.15 < terrain.max_slope < 0.8  # real hills, yet near-nadir views stay unoccluded
    w = terrain.urban_weight
    assert 0.45 < float((w > 0.5).mean()) < 0.55
    assert float((w > 0.95).mean()) >= 0.2 and float((w < 0.05).mean()) >= 0.2

    # busy regions carry many more SIFT keypoints per area than smooth ones
    sift = cv2.SIFT_create()
    win = 256
    counts: dict[str, list[int]] = {"busy": [], "smooth": []}
    for r in range(0, 3200 - win + 1, win):
        for c in range(0, 3200 - win + 1, win):
            ww = w[r : r + win, c : c + win]
            kind = "busy" if ww.min() > 0.95 else "smooth" if ww.max() < 0.05 else None
            if kind and len(counts[kind]) < 6:
                counts[kind].append(len(sift.detect(terrain.texture[r : r + win, c : c + win])))
    assert len(counts["busy"]) == 6 and len(counts["smooth"]) == 6
    busy, smooth = np.mean(counts["busy"]), np.mean(counts["smooth"])
    print(f"SIFT keypoints per {win}^2 texels: busy {busy:.0f}, smooth {smooth:.0f}")
    assert busy > 4 * smooth


def test_queries_follow_the_raster_conventions(terrain: Terrain):
    n0, e0 = terrain.spec.origin_nav_m
    res, px = terrain.spec.height_res_m, terrain.spec.texture_px_per_m
    # elevation node (i, j) at (n0 + i res, e0 + j res); texel (r, c) centre at +0.5 texel
    assert terrain.elevation_at(n0 + 3 * res, e0 + 5 * res) == terrain.elevation_m[3, 5]
    mid = terrain.elevation_at(n0 + 3.5 * res, e0 + 5 * res)
    assert mid == pytest.approx(terrain.elevation_m[3:5, 5].mean())
    assert terrain.texture_at(n0 + 7.5 / px, e0 + 2.5 / px) == terrain.texture[7, 2] / 255.0
    p = terrain.surface_nav(np.array([1.0, 2.0]), np.array([3.0, 4.0]))
    assert p.shape == (2, 3) and np.allclose(p[:, 2], -terrain.elevation_at([1.0, 2.0], [3, 4]))
    assert terrain.contains(0.0, 0.0) and not terrain.contains(n0 - 1.0, 0.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"size_m": (0.0, 100.0)}, "size_m must be positive"),
        ({"size_m": (100.0,)}, "two finite numbers"),
        ({"texture_px_per_m": -1.0}, "texture_px_per_m must be a positive"),
        ({"height_res_m": 0.0}, "height_res_m must be a positive"),
        ({"relief_m": -5.0}, "relief_m must be >= 0"),
        ({"urban_fraction": 1.5}, r"urban_fraction must lie in \[0, 1\]"),
        ({"region_scale_m": float("nan")}, "region_scale_m must be a positive"),
        ({"texture_px_per_m": 100.0}, "lower texture_px_per_m"),
        ({"size_m": (10.0, 10.0), "height_res_m": 20.0}, "exceeds the terrain"),
    ],
)
def test_impossible_specs_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TerrainSpec(**kwargs)


def test_same_seed_same_world_and_images():
    spec = TerrainSpec(size_m=(200.0, 300.0), origin_nav_m=(-100.0, -150.0), relief_m=20.0)
    a, b = (make_terrain(spec, np.random.default_rng(3)) for _ in range(2))
    c = make_terrain(spec, np.random.default_rng(4))
    for name in ("elevation_m", "texture", "urban_weight"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.texture, c.texture)
    cam = _camera(None)
    rays = pixel_rays(cam)
    T = _pose(a, 5.0, -10.0, 60.0, (2.0, -3.0, 20.0))
    ra, rb = (render_terrain_view(t, cam, T, rays=rays) for t in (a, b))
    assert np.array_equal(ra.radiance, rb.radiance)
    assert np.array_equal(ra.depth_m, rb.depth_m, equal_nan=True)


# -- rendering ----------------------------------------------------------------------------------


@pytest.mark.parametrize("rig_name", ["rectified", "distorted"])
def test_rendered_views_agree_with_the_forward_geometry(terrain: Terrain, rigs, rig_name: str):
    """The issue's acceptance check: depth and radiance of both views at the pixels where
    `project_points` puts 1000 random surface points, and the misregistration of busy
    patches measured by phase correlation."""
    rig = rigs[rig_name]
    n_c, e_c = 35.0, -60.0
    T_nav_left = _pose(terrain, n_c, e_c, 100.0, (3.0, -4.0, 25.0))
    views = {
        "left": (rig.left, T_nav_left, rig.rays_left),
        "right": (rig.right, T_nav_left @ rig.T_left_right, rig.rays_right),
    }
    for side, (cam, T_nav_cam, rays) in views.items():
        view = render_terrain_view(terrain, cam, T_nav_cam, rays=rays, want_points=True)
        assert view.valid.all() and view.radiance.dtype == np.float32
        # every hit lies on the surface
        p = view.p_nav_m.reshape(-1, 3).astype(np.float64)
        surface_err = np.abs(p[:, 2] + terrain.elevation_at(p[:, 0], p[:, 1]))
        assert surface_err.max() < 1e-3

        n, e, p_cam, uv = _visible_points(terrain, cam, T_nav_cam, n_c, e_c, 1000)
        depth_rel = np.abs(_bilinear(view.depth_m, uv) / p_cam[:, 2] - 1.0)
        assert depth_rel.max() < 1e-3

        truth = terrain.texture_at(n, e)
        resid = np.abs(_bilinear(view.radiance, uv) - truth).mean()
        resid_1px = np.abs(_bilinear(view.radiance, uv + np.array([1.0, 0.0])) - truth).mean()
        assert resid < 0.5 * resid_1px

        shifts = [
            np.hypot(*_ortho_patch_shift(terrain, cam, T_nav_cam, view.radiance, n_s, e_s))
            for n_s, e_s in _busy_spots(terrain, n_c, e_c, 4)
        ]
        # texels -> pixels: one texel spans F / depth / px_per_m pixels
        px_per_texel = F / float(np.median(p_cam[:, 2])) / terrain.spec.texture_px_per_m
        shift_px = np.mean(shifts) * px_per_texel
        print(
            f"{rig_name} {side}: depth rel err max {depth_rel.max():.1e}, surface err max "
            f"{surface_err.max():.1e} m, radiance resid {resid:.4f} (1 px off: {resid_1px:.4f}),"
            f" misregistration {shift_px:.3f} px"
        )
        assert shift_px < 0.5


def test_misregistration_measure_sees_a_known_shift(terrain: Terrain, rigs):
    rig = rigs["rectified"]
    T = _pose(terrain, 35.0, -60.0, 100.0, (0.0, 0.0, 0.0))
    view = render_terrain_view(terrain, rig.left, T, rays=rig.rays_left)
    n_s, e_s = _busy_spots(terrain, 35.0, -60.0, 1)[0]
    texel = 1.0 / terrain.spec.texture_px_per_m
    base = _ortho_patch_shift(terrain, rig.left, T, view.radiance, n_s, e_s)
    injected = np.array([0.3, -0.5])
    seen = _ortho_patch_shift(terrain, rig.left, T, view.radiance, n_s, e_s, injected * texel)
    np.testing.assert_allclose(base - seen, injected, atol=0.05)


def test_rectified_disparity_and_right_depth(terrain: Terrain, rigs):
    rig = rigs["rectified"]
    n_c, e_c = -120.0, 80.0
    T_nav_left = _pose(terrain, n_c, e_c, 110.0, (-2.0, 3.0, -70.0))
    T_nav_right = T_nav_left @ rig.T_left_right
    n, e, p_left, uv_l = _visible_points(terrain, rig.left, T_nav_left, n_c, e_c, 1000)
    p_nav = terrain.surface_nav(n, e)
    p_right = (invert_T(T_nav_right) @ np.column_stack([p_nav, np.ones(len(p_nav))]).T).T[:, :3]
    uv_r, _ = project_points(rig.right, p_right)
    z = p_left[:, 2]
    np.testing.assert_allclose(uv_l[:, 0] - uv_r[:, 0], F * BASELINE_M / z, atol=1e-6)
    np.testing.assert_allclose(uv_l[:, 1], uv_r[:, 1], atol=1e-6)
    right = render_terrain_view(terrain, rig.right, T_nav_right, rays=rig.rays_right)
    inside = uv_r[:, 0] > 2
    depth_rel = np.abs(_bilinear(right.depth_m, uv_r[inside]) / z[inside] - 1.0)
    assert depth_rel.max() < 1e-3


def test_off_terrain_and_upward_rays_are_invalid(terrain: Terrain, rigs):
    rig = rigs["rectified"]
    n_max = terrain.bounds_nav_m[1]
    # over the northern edge: the upper half of the image (north) sees beyond the terrain
    T = _pose(terrain, n_max - 1.0, 0.0, 100.0, (0.0, 0.0, 0.0))
    view = render_terrain_view(terrain, rig.left, T, rays=rig.rays_left, want_points=True)
    assert view.valid[-1].all() and not view.valid[0].any()
    assert 0.3 < view.valid.mean() < 0.7
    assert np.isnan(view.depth_m[~view.valid]).all() and (view.radiance[~view.valid] == 0).all()
    p = view.p_nav_m[view.valid]
    assert np.all(terrain.contains(p[:, 0], p[:, 1]))
    # pitched up by 80 deg: the top of the image looks above the horizon
    T = _pose(terrain, 0.0, 0.0, 100.0, (0.0, 80.0, 0.0))
    view = render_terrain_view(terrain, rig.left, T, rays=rig.rays_left)
    assert not view.valid[0].any() and view.valid[-1].all()


def test_high_views_use_a_coarser_texture_level(terrain: Terrain):
    """From 350 m a pixel spans ~3 texels: the automatic mip level must be closer than full
    resolution to the image that area-sampling the ground would give (3x3 supersampling)."""
    cam = _camera(None)
    s = 3
    K_big = np.array([[F * s, 0, 376.0 * s + 1.0], [0, F * s, 240.0 * s + 1.0], [0, 0, 1.0]])
    big = CameraModel(W * s, H * s, K_big)
    T = _pose(terrain, 50.0, 30.0, 350.0, (0.0, 0.0, 0.0))
    ref = render_terrain_view(terrain, big, T, texture_level=0).radiance
    ref = cv2.resize(ref, (W, H), interpolation=cv2.INTER_AREA)
    auto = render_terrain_view(terrain, cam, T)
    full = render_terrain_view(terrain, cam, T, texture_level=0)
    assert auto.valid.all()
    err_auto, err_full = (float(np.abs(v.radiance - ref).mean()) for v in (auto, full))
    print(f"350 m: error vs supersampled {err_auto:.4f} (auto level), {err_full:.4f} (level 0)")
    assert err_auto < 0.7 * err_full


def test_bad_inputs_are_refused(terrain: Terrain, rigs):
    cam = rigs["rectified"].left
    with pytest.raises(ValueError, match="4x4"):
        render_terrain_view(terrain, cam, np.eye(3))
    with pytest.raises(ValueError, match="expected"):
        render_terrain_view(terrain, cam, np.eye(4), rays=np.zeros((10, 10, 3)))
    with pytest.raises(ValueError, match="elevation_m has shape"):
        Terrain(terrain.spec, np.zeros((3, 3)), terrain.texture, terrain.urban_weight)
