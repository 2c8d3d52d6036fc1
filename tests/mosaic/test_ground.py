"""Ground surface from landmarks: robust plane, per-region planes, continuity, refusals."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.config import GroundConfig
from cvslam_cli.mosaic.ground import GroundFitError, fit_ground, fit_plane


def _plane_points(rng, n, abc, noise=0.2, extent=100.0):
    ne = rng.uniform(-extent, extent, (n, 2))
    z = abc[0] + abc[1] * ne[:, 0] + abc[2] * ne[:, 1] + rng.normal(0, noise, n)
    return np.c_[ne, z]


def test_plane_is_found_through_outliers_and_walls():
    rng = np.random.default_rng(3)
    abc = np.array([5.0, 0.05, -0.1])
    ground = _plane_points(rng, 400, abc)
    # a wall (vertical plane n = 20) with more points than any other non-ground structure
    wall = np.c_[np.full(150, 20.0), rng.uniform(-50, 50, 150), rng.uniform(-10, 5, 150)]
    junk = rng.uniform(-100, 100, (100, 3))
    pts = np.vstack([ground, wall, junk])
    got, inl = fit_plane(
        pts, inlier_threshold_m=1.0, max_tilt_deg=30.0, rng=rng, below_nav_m=np.array([0, 0, -50.0])
    )
    assert np.all(np.abs(got - abc) < [0.1, 0.002, 0.002]), got
    assert inl[:400].mean() > 0.95 and inl[400:550].mean() < 0.2


def test_only_steep_structure_is_refused():
    rng = np.random.default_rng(0)
    wall = np.c_[np.full(100, 20.0), rng.uniform(-50, 50, 100), rng.uniform(-10, 5, 100)]
    with pytest.raises(GroundFitError, match="horizontal"):
        fit_plane(wall, inlier_threshold_m=0.5, max_tilt_deg=30.0, rng=rng)
    with pytest.raises(GroundFitError, match="at least 3"):
        fit_plane(wall[:2], inlier_threshold_m=0.5, max_tilt_deg=30.0, rng=rng)


def test_flat_ground_keeps_one_plane():
    rng = np.random.default_rng(1)
    pts = _plane_points(rng, 2000, np.array([-3.0, 0.0, 0.0]), extent=150.0)
    cams = np.c_[rng.uniform(-100, 100, (50, 2)), np.full(50, -80.0)]
    g = fit_ground(pts, cams, GroundConfig())
    assert g.local_regions == 0
    assert 1.0 < g.threshold_m < 3.0  # 2 % of the ~90 m from landmark to camera
    n, e = rng.uniform(-300, 300, (2, 50))  # far outside the map too
    np.testing.assert_allclose(g.z_at(n, e), -3.0, atol=0.05)


def test_hill_gets_regional_planes_and_the_surface_is_continuous():
    """A flat plain with a 20 m ramp-shaped hill in one corner: the regions on the hill get
    planes of their own, the surface follows the hill far better than the global plane,
    and it has no steps between regions."""
    rng = np.random.default_rng(2)
    ne = rng.uniform(-150, 150, (6000, 2))

    def true_z(n, e):  # NED: a hill is negative z
        return -np.clip((n - 20.0) * 0.3, 0.0, 20.0) * (e > 40.0)

    pts = np.c_[ne, true_z(ne[:, 0], ne[:, 1]) + rng.normal(0, 0.3, len(ne))]
    cams = np.c_[rng.uniform(-150, 150, (80, 2)), np.full(80, -100.0)]
    g = fit_ground(pts, cams, GroundConfig())
    assert g.local_regions >= 4
    # on the hill, away from its edges
    n, e = np.meshgrid(np.linspace(40, 140, 30), np.linspace(60, 140, 30))
    err_model = np.abs(g.z_at(n, e) - true_z(n, e))
    a, b, c = g.global_abc
    err_plane = np.abs(a + b * n + c * e - true_z(n, e))
    assert np.median(err_model) < 0.25 * np.median(err_plane)
    assert np.median(err_model) < 2.0
    # continuity: along a line through many regions, neighbouring samples 0.1 m apart
    # never differ by more than the steepest slope allows
    n_line = np.linspace(-150, 150, 3001)
    z = g.z_at(n_line, np.full_like(n_line, 90.0))
    assert np.max(np.abs(np.diff(z))) < 0.1


def test_ground_robot_scene_the_ground_not_the_box_tops():
    """A yard seen from 0.5 m: ground points at z = 0, as many points on box tops 1 m up and
    walls; the fit must pick the ground (below the cameras) with a centimetre threshold."""
    rng = np.random.default_rng(4)
    ground = np.c_[rng.uniform(-20, 20, (800, 2)), rng.normal(0, 0.02, 800)]
    tops = np.c_[rng.uniform(-20, 20, (900, 2)), np.full(900, -1.0) + rng.normal(0, 0.02, 900)]
    walls = np.c_[np.full(600, 15.0), rng.uniform(-20, 20, 600), rng.uniform(-2.5, 0, 600)]
    cams = np.c_[rng.uniform(-15, 15, (60, 2)), np.full(60, -0.5)]
    # cameras between the box tops and the ground: planes above them are refused
    cams[:, 2] = -0.5
    g = fit_ground(np.vstack([ground, tops, walls]), cams, GroundConfig())
    assert abs(g.global_abc[0]) < 0.03 and np.hypot(*g.global_abc[1:]) < 0.005
    assert g.threshold_m < 0.3
