"""A mixed team over the yard: UAVs flying over it (validation, the ground beyond its walls)
and `configs/scenarios/mixed_yard.yaml`, whose two UAVs and two ground robots run in one
filter and share landmarks across the kinds (BENCHMARKS.md, "Fuse: a mixed team (issue 20)")."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from cvslam_cli.errors import ConfigError
from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.map_file import load_map
from cvslam_cli.io.observations_file import load_observations
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.sim.scenario import SCENARIO_DIR, load_scenario
from cvslam_cli.sim.stage import MIN_CLEARANCE_M, run
from cvslam_cli.sim.vehicles import build_path
from cvslam_cli.sim.yard import YardSpec, make_yard, render_yard_view
from tests.scenarios import SMALL_CAMERA

MIXED = SCENARIO_DIR / "mixed_yard.yaml"
KIND = {"uav1": "uav", "uav2": "uav", "robot1": "ugv", "robot2": "ugv"}


def _nadir_camera() -> CameraModel:
    K = np.array([[112.5, 0.0, 93.5], [0.0, 112.5, 59.5], [0.0, 0.0, 1.0]])
    return CameraModel(188, 120, K, P=np.hstack([K, np.zeros((3, 1))]))


def _small_mixed(tmp_path: Path, **uav1: object) -> Path:
    """A 20 m yard (coarse textures, 6 m of ground beyond the walls) with a UAV flying out
    over its east wall and a robot in its lane; `uav1` replaces keys of the UAV's section."""
    sc = {
        "name": "small_mixed",
        "mode": "landmarks",
        "duration_s": 2.0,
        "seed": 2,
        "world": "yard",
        "yard": {
            "size_m": [20.0, 20.0],
            "origin_nav_m": [-10.0, -10.0],
            "n_obstacles": 2,
            "obstacle_clearance_m": 3.0,
            "texture_px_per_m": 10.0,
            "ground_px_per_m": 8.0,
            "ground_margin_m": 6.0,
        },
        "vehicles": {
            "uav1": {
                "kind": "uav",
                "speed_m_s": 3.0,
                "camera": dict(SMALL_CAMERA, baseline_m=0.4),
                "waypoints_nav_m": [[-6, 5, -8], [-6, 14, -8]],
                **uav1,
            },
            "robot1": {
                "kind": "ugv",
                "speed_m_s": 1.0,
                "camera": dict(SMALL_CAMERA, mount="forward", tilt_deg=10.0, baseline_m=0.3),
                "waypoints_nav_m": [[-8.5, -8, 0], [-8.5, 8, 0]],
            },
        },
    }
    path = tmp_path / "small_mixed.yaml"
    path.write_text(yaml.safe_dump(sc))
    return path


def test_ground_beyond_the_walls_is_textured():
    spec = YardSpec(size_m=(20.0, 16.0), origin_nav_m=(0.0, 0.0), n_obstacles=0)
    plain = make_yard(spec, np.random.default_rng(3))
    wide = make_yard(replace(spec, ground_margin_m=5.0), np.random.default_rng(3))
    ppm = spec.ground_px_per_m
    assert plain.ground_texture.shape == (20 * ppm, 16 * ppm)  # no margin: as before
    assert wide.ground_texture.shape == (30 * ppm, 26 * ppm)
    assert wide.spec.ground_origin_nav_m == (-5.0, -5.0)
    # walls where they were; beyond the south wall, texture varies with the distance from it
    # (without a margin the edge texel repeats)
    assert [w.p0_ne.tolist() for w in wide.walls] == [w.p0_ne.tolist() for w in plain.walls]
    n_out, e = np.linspace(-4.5, -0.5, 40), np.full(40, 8.0)
    assert np.ptp(plain.ground_texture_at(n_out, e)) < 1e-6
    assert np.std(wide.ground_texture_at(n_out, e)) > 0.02
    # a camera 8 m up over the south wall, looking straight down, sees ground on both sides
    R_down = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # image up = north
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_down, [0.0, 8.0, -8.0]
    view = render_yard_view(wide, _nadir_camera(), T, want_points=True)
    assert view.valid.all()
    outside = view.p_nav_m[..., 0] < -0.5
    assert 0.2 < outside.mean() < 0.8
    assert np.std(view.radiance[outside]) > 0.02
    for margin in (-1.0, 500.0):
        with pytest.raises(ValueError, match="ground_margin_m"):
            make_yard(replace(spec, ground_margin_m=margin), np.random.default_rng(0))


def test_uav_over_the_yard_flies_over_obstacles_not_below_the_walls(tmp_path):
    sc = load_scenario(_small_mixed(tmp_path))
    summary = run(sc, tmp_path / "ok")  # over the east wall: no obstacle to a UAV
    assert summary.vehicles["uav1"].imu_samples > 0 and summary.vehicles["uav1"].observations
    assert summary.vehicles["robot1"].odometry_samples > 0
    # world.npz: the textured ground (yard and margin), as the mosaic's truth reads it; ground
    # landmarks on all of it, walls where the yard's are
    with np.load(tmp_path / "ok" / "truth" / "world.npz") as world:
        np.testing.assert_allclose(world["origin_nav_m"], [-16.0, -16.0])
        np.testing.assert_allclose(world["size_m"], [32.0, 32.0])
        assert world["ground_texture"].shape == (32 * 8, 32 * 8)
        assert np.abs(world["wall_segments_ne"][:4]).max() == 10.0
    lm = np.loadtxt(tmp_path / "ok" / "truth" / "landmarks.csv", delimiter=",", skiprows=1)
    ground = lm[lm[:, 3] == 0.0, 1:3]
    assert np.abs(ground).max() > 14.0 and np.abs(ground).max() <= 16.0
    low = [[-6, -6, -(2.5 + MIN_CLEARANCE_M - 1.0)], [6, 6, -(2.5 + MIN_CLEARANCE_M - 1.0)]]
    out = [[-6, 18, -8], [-6, 30, -8]]  # beyond the 6 m of ground outside the east wall
    for waypoints, message in (
        (low, "vehicles.uav1.waypoints_nav_m: the vehicle is 4.0 m above the yard's tallest"),
        (out, "vehicles.uav1.waypoints_nav_m: the path leaves the yard's ground at t ="),
    ):
        with pytest.raises(ConfigError) as exc:
            run(load_scenario(_small_mixed(tmp_path, waypoints_nav_m=waypoints)), tmp_path / "x")
        assert message in str(exc.value) and "\n" not in str(exc.value)


def test_mixed_yard_geometry():
    sc = load_scenario(MIXED)
    assert sc.world == "yard" and {n: v.kind for n, v in sc.vehicles.items()} == KIND
    yard = sc.yard
    (n0, e0), (sn, se) = yard.origin_nav_m, yard.size_m
    lo_obst = n0 + yard.obstacle_clearance_m  # obstacles stay inside this square (any seed)
    for name, v in sc.vehicles.items():
        path = build_path(name, v, sc.duration_s, str(MIXED))
        p = path.sample(np.arange(v.start_s, sc.duration_s, 0.25)).p_nav_m
        if v.kind == "uav":  # over the obstacles, 5 m above the walls, inside the yard
            assert np.all(-p[:, 2] >= yard.wall_height_m + MIN_CLEARANCE_M)
            assert v.camera.mount == "forward" and v.camera.tilt_deg >= 30.0
        else:  # in the lane between the walls and the obstacles' square
            assert e0 == n0 and se == sn
            side = np.max(np.abs(p[:, :2] - (n0 + sn / 2)), axis=1)
            assert np.all(side < sn / 2 - 2.0) and np.all(side > abs(lo_obst) + 2.0)
        assert np.all(np.abs(p[:, :2]) < sn / 2)


@pytest.fixture(scope="module")
def short_mixed_run(tmp_path_factory) -> Path:
    """4 s of mixed_yard in landmark mode (uav2 from 1 s; coarse textures: only the
    landmarks are used), fused with all four vehicles in one filter."""
    from cvslam_cli.cli import main

    tmp = tmp_path_factory.mktemp("mixed")
    out = tmp / "run"
    short = ["mode=landmarks", "duration_s=4", "vehicles.uav2.start_s=1"]
    coarse = ["yard.ground_px_per_m=8", "yard.texture_px_per_m=10"]
    sets = [a for kv in short + coarse for a in ("--set", kv)]
    for args in (["-q", "simulate", "mixed_yard", "-o", str(out), *sets], ["-q", "fuse", str(out)]):
        with pytest.raises(SystemExit) as exc:
            main(args)
        assert exc.value.code in (0, None), args
    return out


def test_one_filter_holds_both_kinds(short_mixed_run):
    import pandas as pd

    timeline = pd.read_csv(short_mixed_run / "fuse" / "timeline.csv")
    assert set(timeline.vehicle) == set(KIND)
    # the joint state: two 3-DOF odometry blocks and two 15-state INS blocks, no landmark yet
    first = timeline.iloc[0]
    assert first.state_size == 2 * 3 + 2 * 15 and first.landmarks_in_state == 0
    for name in KIND:
        est = read_tum(short_mixed_run / "fuse" / f"{name}.tum")
        truth = read_tum(short_mixed_run / "truth" / f"{name}.tum")
        dead = read_tum(short_mixed_run / "fuse" / f"{name}_deadreckoning.tum")
        idx = np.searchsorted(truth.stamps_ns, est.stamps_ns - 1000)  # TUM: float seconds
        err = np.linalg.norm(est.p_nav_m - truth.p_nav_m[idx], axis=1)
        err_dead = np.linalg.norm(dead.p_nav_m - truth.p_nav_m[idx], axis=1)
        assert err.max() < 0.3, name
        if KIND[name] == "uav":  # the IMU drifts faster than the filter
            assert err[-1] < 0.5 * err_dead[-1], name
        else:  # a ground robot stays on the ground plane
            np.testing.assert_allclose(est.p_nav_m[:, 2], truth.p_nav_m[0, 2], atol=1e-9)


def test_kinds_share_landmarks(short_mixed_run):
    """Landmarks one kind mapped are observed by the other, both ways, and every such
    observation is of the same simulated landmark (its true id)."""
    obs = load_observations(short_mixed_run / "fuse" / "observations.npz")
    archive = load_map(short_mixed_run / "fuse" / "map.npz")
    true_of = dict(zip(archive.landmark_id.tolist(), archive.true_id.tolist(), strict=True))
    kind = np.array([KIND[obs.vehicles[i]] for i in obs.vehicle])
    order = np.lexsort((obs.vehicle, obs.stamp_ns))
    first_kind: dict[int, str] = {}
    for i in order:
        first_kind.setdefault(int(obs.landmark_id[i]), kind[i])
    made_by = np.array([first_kind[int(i)] for i in obs.landmark_id])
    cross = made_by != kind
    for a, b in (("uav", "ugv"), ("ugv", "uav")):
        sel = cross & (made_by == a)
        assert len(set(obs.landmark_id[sel].tolist())) >= 10, (a, b)
    features = {v: load_features(short_mixed_run / "features" / f"{v}.npz")[0] for v in KIND}
    right = 0
    for i in np.flatnonzero(cross):
        fs = features[obs.vehicles[obs.vehicle[i]]]
        sl = fs.frame_matches(int(np.searchsorted(fs.frame_stamp_ns, obs.stamp_ns[i])))
        uv = fs.left_uv_px[fs.match_left[sl]]
        j = np.flatnonzero(np.all(np.abs(uv - obs.z_px[i, :2]) < 1e-9, axis=1))
        assert len(j) == 1
        right += int(fs.match_landmark_id[sl][j[0]] == true_of[int(obs.landmark_id[i])])
    assert right >= 0.98 * cross.sum() and cross.sum() > 100
