"""`cvslam simulate`: a scenario in, one MCAP log per vehicle and the ground truth out.

Output directory (written as `<out>.partial` and renamed when complete):
```
<out>/scenario.yaml            the resolved scenario (seed and duration included)
<out>/<vehicle>.mcap           ROS 2 log: stereo images + CameraInfo (images mode), IMU
                               (UAV) or wheel odometry (UGV), ground truth, /tf_static
<out>/truth/<vehicle>.tum      true body pose in the nav frame (NED), TUM format
<out>/truth/<vehicle>_imu.npz  true IMU biases over time (UAV)
<out>/truth/world.npz          terrain: elevation grid, orthophoto, urban weight, geometry;
                               yard: ground texture (origin_nav_m, size_m: the textured
                               ground, the yard and its ground_margin_m) and the walls
<out>/truth/<vehicle>_depth.npz per-pixel depth of every left image (outputs.depth)
<out>/truth/landmarks.csv      landmark mode: id, x, y, z (nav frame)
<out>/features/<vehicle>.npz   landmark mode: observations in the extract feature format
```
Stamps are integer nanoseconds from `SIM_EPOCH_NS` plus scenario time. Randomness comes
from one seed through independent streams per world, vehicle, sensor and frame, so the
output is byte-identical for the same scenario and seed, whatever the number of workers.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from tqdm import tqdm

from cvslam_cli.errors import ConfigError, CvslamError
from cvslam_cli.geometry.camera import CameraModel, StereoRig, rig_calibration
from cvslam_cli.geometry.projection import pixel_rays
from cvslam_cli.geometry.rotations import matrix_to_quat_xyzw
from cvslam_cli.io.atomic import atomic_dir, check_writable, write_text_atomic
from cvslam_cli.io.features_file import save_features
from cvslam_cli.io.mcap_writer import LogWriter
from cvslam_cli.io.names import NAV_FRAME_ID, TF_STATIC_TOPIC, VehicleNames, vehicle_names
from cvslam_cli.io.npz import NpzWriter, save_npz
from cvslam_cli.io.run_layout import SimLayout
from cvslam_cli.io.trajectory import write_tum
from cvslam_cli.parallel import STATE, ordered_map
from cvslam_cli.records.features import FeatureSetBuilder
from cvslam_cli.records.poses import PoseTable
from cvslam_cli.sim.imu import ImuData, simulate_imu
from cvslam_cli.sim.landmarks import LandmarkWorld, make_world, observe_frame, seen_by
from cvslam_cli.sim.odometry import OdometryData, simulate_odometry
from cvslam_cli.sim.render import RenderResult, photometric
from cvslam_cli.sim.scenario import Scenario, SimVehicle, dump_scenario
from cvslam_cli.sim.terrain import Terrain, make_terrain, render_terrain_view
from cvslam_cli.sim.vehicles import VehiclePath, build_path, build_rig, camera_poses, sample_times
from cvslam_cli.sim.yard import Yard, make_yard, render_yard_view

log = logging.getLogger("cvslam")

SIM_EPOCH_NS = 1_700_000_000 * 1_000_000_000
GRAVITY_NAV = np.array([0.0, 0.0, 9.80665])
# stream ids of the random generators (with the seed and the vehicle index)
_WORLD, _IMU, _ODOM, _FRAME, _LANDMARKS, _OFFSETS = 0, 1, 2, 3, 4, 5

World = Terrain | Yard
MIN_CLEARANCE_M = 5.0  # least height of a UAV above the ground (terrain) or the walls (yard)


def stamp_ns(t_s: np.ndarray | float) -> np.ndarray:
    return SIM_EPOCH_NS + np.rint(np.asarray(t_s, dtype=float) * 1e9).astype(np.int64)


@dataclass(frozen=True)
class VehicleSummary:
    stereo_frames: int
    imu_samples: int
    odometry_samples: int
    ground_truth_poses: int
    distance_m: float
    observations: int


@dataclass(frozen=True)
class SimSummary:
    out_dir: Path
    vehicles: dict[str, VehicleSummary]
    wall_time_s: float


@dataclass(frozen=True, eq=False)
class _Vehicle:
    index: int
    names: VehicleNames
    spec: SimVehicle
    rig: StereoRig
    path: VehiclePath


# ----------------------------------------------------------------------------- world


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


def build_world(sc: Scenario) -> World:
    rng = _rng(sc.seed, _WORLD)
    try:
        return make_terrain(sc.terrain, rng) if sc.world == "terrain" else make_yard(sc.yard, rng)
    except ValueError as exc:
        raise ConfigError(f"scenario {sc.name}: {sc.world}: {exc}") from None


def render_view(
    world: World,
    cam: CameraModel,
    T_nav_cam: np.ndarray,
    rays: np.ndarray,
    want_points: bool = False,
) -> RenderResult:
    if isinstance(world, Yard):
        return render_yard_view(world, cam, T_nav_cam, rays=rays, want_points=want_points)
    return render_terrain_view(world, cam, T_nav_cam, rays=rays, want_points=want_points)


def _coarse(cam: CameraModel, factor: int = 8) -> CameraModel:
    S = np.diag([1.0 / factor, 1.0 / factor, 1.0])
    K = S @ cam.K
    K[0, 2] = (cam.K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (cam.K[1, 2] + 0.5) / factor - 0.5
    return replace(
        cam, width=max(2, cam.width // factor), height=max(2, cam.height // factor), K=K, P=None
    )


def _check_uav_over_yard(yard: Yard, key: str, t_s: np.ndarray, p_nav_m: np.ndarray) -> None:
    """A UAV over the yard stays over its textured ground (the yard and its ground margin;
    beyond, the ground has no texture of its own, nor landmarks) and at least
    `MIN_CLEARANCE_M` above its tallest wall (walls and obstacles are no obstacles to it)."""
    (n0, e0), (sn, se) = yard.spec.ground_origin_nav_m, yard.spec.ground_size_m
    n, e = p_nav_m[:, 0], p_nav_m[:, 1]
    inside = (n >= n0) & (n <= n0 + sn) & (e >= e0) & (e <= e0 + se)
    if not inside.all():
        i = int(np.argmin(inside))
        raise ConfigError(
            f"{key}.waypoints_nav_m: the path leaves the yard's ground at t = {t_s[i]:.1f} s "
            f"(north {n[i]:.1f} m, east {e[i]:.1f} m)"
        )
    top_m = max(w.height_m for w in yard.walls)
    clearance = -p_nav_m[:, 2] - top_m
    if clearance.min() < MIN_CLEARANCE_M:
        i = int(np.argmin(clearance))
        raise ConfigError(
            f"{key}.waypoints_nav_m: the vehicle is {clearance[i]:.1f} m above the "
            f"yard's tallest wall ({top_m:g} m) at t = {t_s[i]:.1f} s (at least "
            f"{MIN_CLEARANCE_M:g} m needed)"
        )


def check_vehicle(world: World, v: _Vehicle, duration_s: float, source: str) -> None:
    """One-line errors for a path that leaves the world or a camera that does not see it."""
    key = f"{source}: vehicles.{v.names.vehicle}"
    t = sample_times(v.spec.start_s, duration_s, 2.0)
    m = v.path.sample(t)
    n, e = m.p_nav_m[:, 0], m.p_nav_m[:, 1]
    if isinstance(world, Terrain):
        inside = world.contains(n, e)
        if not inside.all():
            i = int(np.argmin(inside))
            raise ConfigError(
                f"{key}.waypoints_nav_m: the path leaves the terrain at t = "
                f"{t[i]:.1f} s (north {n[i]:.0f} m, east {e[i]:.0f} m)"
            )
        agl = -m.p_nav_m[:, 2] - world.elevation_at(n, e)
        if agl.min() < MIN_CLEARANCE_M:
            i = int(np.argmin(agl))
            raise ConfigError(
                f"{key}.waypoints_nav_m: the vehicle is {agl[i]:.1f} m above the "
                f"ground at t = {t[i]:.1f} s (at least {MIN_CLEARANCE_M:g} m needed)"
            )
    elif v.spec.kind == "uav":  # over the yard: inside its footprint, above its walls
        _check_uav_over_yard(world, key, t, m.p_nav_m)
    else:
        ok = np.array([world.free_space_ok(a, b, 0.3) for a, b in zip(n, e, strict=True)])
        if not ok.all():
            i = int(np.argmin(ok))
            raise ConfigError(
                f"{key}.waypoints_nav_m: the path runs into a wall or leaves "
                f"the yard at t = {t[i]:.1f} s (north {n[i]:.1f} m, east "
                f"{e[i]:.1f} m)"
            )
    coarse = _coarse(v.rig.left)
    rays = pixel_rays(coarse)
    T_left, _, _ = camera_poses(v.path, v.rig, t[:: max(1, len(t) // 20)])
    seen = np.array([render_view(world, coarse, T, rays).valid.mean() for T in T_left])
    if np.median(seen) < 0.25:
        raise ConfigError(
            f"{key}.camera: the camera sees the ground in only "
            f"{100 * np.median(seen):.0f}% of the image (median over the path); "
            "check camera.mount, tilt_deg and the altitude"
        )


# ----------------------------------------------------------------------------- frames


def _render_pair(job: tuple[int, int, np.ndarray, np.ndarray]) -> tuple[np.ndarray, ...]:
    """(left image, right image, left depth) of one frame of vehicle `vi`; the world and
    the vehicle's rig come from `parallel.STATE`."""
    vi, k, T_left, T_right = job
    world, sc = STATE["world"], STATE["scenario"]
    rig, rays = STATE["rig"], STATE["rays"]
    rng = _rng(sc.seed, vi, _FRAME, k)
    ph = sc.photometry
    images = []
    depth = None
    for cam, T, r in ((rig.left, T_left, rays[0]), (rig.right, T_right, rays[1])):
        res = render_view(world, cam, T, r)
        gain = 1.0 + ph.gain_sigma * rng.standard_normal()
        offset = ph.offset_sigma * rng.standard_normal()
        images.append(
            photometric(
                res.radiance, gain=gain, offset=offset, noise_sigma=ph.noise_sigma_dn, rng=rng
            )
        )
        if depth is None:
            depth = res.depth_m
    return images[0], images[1], depth


# ----------------------------------------------------------------------------- vehicle


@dataclass(frozen=True, eq=False)
class _Sensors:
    """One vehicle's simulated data: camera stamps (F,) and left/right camera poses
    (F, 4, 4), IMU (UAV) or odometry (UGV), the ground truth, and the interleaving order
    of all their messages."""

    t_cam: np.ndarray
    cam_ns: np.ndarray
    T_left: np.ndarray
    T_right: np.ndarray
    imu: ImuData | None
    odo: OdometryData | None
    gt_table: PoseTable
    distance_m: float
    streams: list[tuple[np.ndarray, int, str]]  # (stamps, order at equal stamps, kind)


def _sensors(sc: Scenario, v: _Vehicle) -> _Sensors:
    spec, rig = v.spec, v.rig
    t_end = sc.duration_s
    t_cam = sample_times(spec.start_s, t_end, spec.camera.rate_hz)
    cam_ns = stamp_ns(t_cam)
    T_left, T_right, _ = camera_poses(v.path, rig, t_cam)
    streams: list[tuple[np.ndarray, int, str]] = [(cam_ns, 1, "frame")]
    imu = odo = None
    if spec.kind == "uav":
        t_imu = sample_times(spec.start_s, t_end, spec.imu_rate_hz)
        imu = simulate_imu(v.path, t_imu, spec.imu, _rng(sc.seed, v.index, _IMU))
        streams.append((stamp_ns(t_imu), 0, "imu"))
    else:
        t_odo = sample_times(spec.start_s, t_end, spec.odometry_rate_hz)
        odo = simulate_odometry(v.path, t_odo, spec.odometry, _rng(sc.seed, v.index, _ODOM))
        streams.append((stamp_ns(t_odo), 0, "odom"))
    t_gt = t_cam if spec.ground_truth_at == "camera" or imu is None else imu.t_s
    gt = v.path.sample(t_gt)
    gt_table = PoseTable(stamp_ns(t_gt), gt.p_nav_m, matrix_to_quat_xyzw(gt.C_nav_body))
    streams.append((gt_table.stamps_ns, 2, "gt"))
    dist = float(np.sum(np.linalg.norm(np.diff(gt.p_nav_m, axis=0), axis=1)))
    return _Sensors(t_cam, cam_ns, T_left, T_right, imu, odo, gt_table, dist, streams)


def _messages(streams: list[tuple[np.ndarray, int, str]]) -> Iterator[tuple[str, int, int]]:
    """(kind, index in its stream, stamp_ns) of every message in stamp order (at equal
    stamps: motion, then the frame, then the ground truth)."""
    stamps = np.concatenate([s for s, _, _ in streams])
    order_key = np.concatenate([np.full(len(s), o) for s, o, _ in streams])
    kinds = np.concatenate([np.full(len(s), i) for i, (s, _, _) in enumerate(streams)])
    index = np.concatenate([np.arange(len(s)) for s, _, _ in streams])
    order = np.lexsort((order_key, stamps))
    kind_names = [k for _, _, k in streams]
    for j in order:
        yield kind_names[kinds[j]], int(index[j]), int(stamps[j])


def _write_log_header(lw: LogWriter, sc: Scenario, v: _Vehicle, first_ns: int) -> None:
    """The log's metadata and the cameras' mounting (/tf_static)."""
    names, rig = v.names, v.rig
    lw.add_metadata(
        "cvslam.sim",
        {
            "scenario": sc.name,
            "seed": str(sc.seed),
            "vehicle": names.vehicle,
            "kind": v.spec.kind,
            "mode": sc.mode,
            "nav_frame": "NED",
            "body_frame": "FRD",
            "stamp_epoch_ns": str(SIM_EPOCH_NS),
            "conversion": "simulated directly in the nav frame (NED); body frame FRD",
        },
    )
    lw.write_tf_static(
        TF_STATIC_TOPIC,
        first_ns,
        [
            (names.body_frame, names.left_frame, rig.left.T_body_cam),
            (names.body_frame, names.right_frame, rig.right.T_body_cam),
        ],
    )


def _write_motion_or_truth(
    lw: LogWriter, kind: str, i: int, st: int, v: _Vehicle, s: _Sensors
) -> None:
    """Message `i` of the IMU, odometry or ground-truth stream."""
    spec, names, topics = v.spec, v.names, v.names.topics
    if kind == "imu":
        imu = s.imu
        assert imu is not None
        lw.write_imu(
            topics.imu,
            st,
            imu.gyro_rad_s[i],
            imu.accel_m_s2[i],
            names.body_frame,
            gyro_var=(spec.imu.gyro_noise_density**2) * spec.imu_rate_hz,
            accel_var=(spec.imu.accel_noise_density**2) * spec.imu_rate_hz,
        )
    elif kind == "odom":
        odo = s.odo
        assert odo is not None
        yaw = odo.yaw_rad[i]
        lw.write_odometry(
            topics.odom,
            st,
            f"{names.vehicle}/odom",
            names.body_frame,
            [odo.x_m[i], odo.y_m[i], 0.0],
            [0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)],
            [odo.v_forward_m_s[i], 0.0, 0.0],
            [0.0, 0.0, odo.yaw_rate_rad_s[i]],
        )
    else:
        gt = s.gt_table
        lw.write_pose(topics.ground_truth, st, gt.p_nav_m[i], gt.q_nav_body_xyzw[i], NAV_FRAME_ID)


def _write_frame(
    lw: LogWriter,
    i: int,
    st: int,
    v: _Vehicle,
    rendered: Iterator[tuple[np.ndarray, ...]] | None,
    depth_writer: NpzWriter | None,
    observe: Callable[[int, int], int],
) -> int:
    """Camera frame `i`: the camera infos, then the rendered images (and depth), or in
    landmark mode the landmarks' observations (`observe`); the observations made."""
    names, rig, topics = v.names, v.rig, v.names.topics
    lw.write_camera_info(topics.left_info, st, rig.left)
    lw.write_camera_info(topics.right_info, st, rig.right)
    if rendered is None:
        return observe(i, st)
    left, right, depth = next(rendered)
    lw.write_image(topics.left_image, st, left, names.left_frame)
    lw.write_image(topics.right_image, st, right, names.right_frame)
    if depth_writer is not None:
        depth_writer.add(f"frame_{i:06d}", depth.astype(np.float16))
    return 0


def _write_truth(out: SimLayout, sc: Scenario, v: _Vehicle, s: _Sensors) -> None:
    """The true trajectory and, for a UAV, the true IMU biases over time."""
    vehicle = v.names.vehicle
    write_tum(
        out.true_trajectory(vehicle),
        s.gt_table,
        header=f"ground truth of {vehicle} (body in nav frame, NED), scenario "
        f"{sc.name}, seed {sc.seed}",
    )
    if s.imu is not None:
        save_npz(
            out.true_imu_biases(vehicle),
            {
                "stamp_ns": stamp_ns(s.imu.t_s),
                "gyro_bias_rad_s": s.imu.gyro_bias_rad_s,
                "accel_bias_m_s2": s.imu.accel_bias_m_s2,
            },
        )


def _write_vehicle(
    out: SimLayout,
    sc: Scenario,
    v: _Vehicle,
    landmarks: LandmarkWorld | None,
    workers: int,
    progress: bool,
    render_state: dict[str, Any],
) -> VehicleSummary:
    """One vehicle's log (messages in stamp order), truth and, in landmark mode, features."""
    s = _sensors(sc, v)
    rig, vehicle = v.rig, v.names.vehicle
    images_mode = sc.mode == "images"
    rendered = None
    if images_mode:
        jobs = [(v.index, k, s.T_left[k], s.T_right[k]) for k in range(len(s.t_cam))]
        state = {**render_state, "rig": rig, "rays": (pixel_rays(rig.left), pixel_rays(rig.right))}
        rendered = ordered_map(
            _render_pair,
            jobs,
            workers=workers,
            state=state,
            describe=lambda job: f"rendering {vehicle} frame {job[1]}",
        )
    builder = FeatureSetBuilder(vehicle, rig_calibration(rig))
    lm_rng = _rng(sc.seed, v.index, _LANDMARKS)
    seen = (
        None
        if landmarks is None
        else seen_by(landmarks, sc.landmarks.observer_offset_m, _rng(sc.seed, v.index, _OFFSETS))
    )

    def observe(i: int, st: int) -> int:
        assert seen is not None
        left_kp, right_kp, matches = observe_frame(seen, rig, s.T_left[i], sc.landmarks, lm_rng)
        builder.add_frame(st, left_kp, right_kp, matches)
        return len(matches["landmark_id"])

    n_observations = 0
    with contextlib.ExitStack() as stack:
        depth_writer = (
            stack.enter_context(NpzWriter(out.true_depth(vehicle)))
            if images_mode and sc.outputs.depth
            else None
        )
        bar = stack.enter_context(
            tqdm(
                total=len(s.t_cam),
                desc=f"simulate {vehicle}",
                unit="frame",
                disable=None if progress else True,
                leave=False,
            )
        )
        with LogWriter(out.log(vehicle)) as lw:
            _write_log_header(lw, sc, v, int(s.cam_ns[0]))
            for kind, i, st in _messages(s.streams):
                if kind == "frame":
                    n_observations += _write_frame(lw, i, st, v, rendered, depth_writer, observe)
                    bar.update(1)
                else:
                    _write_motion_or_truth(lw, kind, i, st, v, s)
    _write_truth(out, sc, v, s)
    if not images_mode:
        save_features(
            builder.build(),
            out.feature_file(vehicle),
            {
                "producer": "cvslam simulate (landmark mode)",
                "scenario": sc.name,
                "seed": sc.seed,
                "landmarks": dump_scenario(sc)["landmarks"],
            },
        )
    return VehicleSummary(
        len(s.t_cam),
        0 if s.imu is None else len(s.imu.t_s),
        0 if s.odo is None else len(s.odo.t_s),
        len(s.gt_table),
        s.distance_m,
        n_observations,
    )


# ----------------------------------------------------------------------------- truth


def _landmark_world(sc: Scenario, world: World) -> LandmarkWorld:
    rng = _rng(sc.seed, _WORLD, _LANDMARKS)
    dens = sc.landmarks.density_per_100m2 / 100.0
    if isinstance(world, Terrain):
        (n0, e0), (sn, se) = world.spec.origin_nav_m, world.spec.size_m
        count = int(rng.poisson(dens * sn * se))
        n, e = rng.uniform(n0, n0 + sn, count), rng.uniform(e0, e0 + se, count)
        return make_world(world.surface_nav(n, e), rng)
    (n0, e0), (sn, se) = world.spec.ground_origin_nav_m, world.spec.ground_size_m
    pts = []
    count = int(rng.poisson(dens * sn * se))
    pts.append(
        np.column_stack(
            [rng.uniform(n0, n0 + sn, count), rng.uniform(e0, e0 + se, count), np.zeros(count)]
        )
    )
    segs, heights = [], []
    for w in world.walls:
        p0, p1 = np.asarray(w.p0_ne, float), np.asarray(w.p1_ne, float)
        length = float(np.linalg.norm(p1 - p0))
        k = int(rng.poisson(dens * 4 * length * w.height_m))  # walls are feature-rich
        s, h = rng.uniform(0, 1, k), rng.uniform(0.05, 0.95, k) * w.height_m
        ne = p0 + s[:, None] * (p1 - p0)
        pts.append(np.column_stack([ne, -h]))
        segs.append([p0, p1])
        heights.append(w.height_m)
    return make_world(np.vstack(pts), rng, (np.asarray(segs, float), np.asarray(heights, float)))


def _write_world(out: SimLayout, world: World) -> None:
    if isinstance(world, Terrain):
        save_npz(
            out.world,
            {
                "kind": np.array("terrain"),
                "elevation_m": world.elevation_m,
                "texture": world.texture,
                "urban_weight": world.urban_weight,
                "origin_nav_m": np.asarray(world.spec.origin_nav_m, float),
                "size_m": np.asarray(world.spec.size_m, float),
                "height_res_m": np.array(world.spec.height_res_m),
                "texture_px_per_m": np.array(world.spec.texture_px_per_m),
            },
        )
    else:
        save_npz(
            out.world,
            {
                "kind": np.array("yard"),
                "ground_texture": world.ground_texture,
                "origin_nav_m": np.asarray(world.spec.ground_origin_nav_m, float),
                "size_m": np.asarray(world.spec.ground_size_m, float),
                "ground_px_per_m": np.array(world.spec.ground_px_per_m),
                "wall_segments_ne": np.array([[w.p0_ne, w.p1_ne] for w in world.walls], float),
                "wall_heights_m": np.array([w.height_m for w in world.walls], float),
            },
        )


# ----------------------------------------------------------------------------- run


def _vehicles(sc: Scenario, world: World, source: str) -> list[_Vehicle]:
    """The scenario's vehicles in name order, each checked against the world."""
    vehicles = []
    for i, (name, spec) in enumerate(sorted(sc.vehicles.items())):
        names = vehicle_names(name, ConfigError)
        rig = build_rig(name, spec.camera)
        v = _Vehicle(i, names, spec, rig, build_path(name, spec, sc.duration_s, source))
        check_vehicle(world, v, sc.duration_s, source)
        vehicles.append(v)
    return vehicles


def _landmarks_csv(landmarks: LandmarkWorld) -> str:
    ids = np.arange(len(landmarks.p_nav_m))
    lines = ["id,x_m,y_m,z_m"] + [
        f"{i},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}" for i, p in zip(ids, landmarks.p_nav_m, strict=True)
    ]
    return "\n".join(lines) + "\n"


def run(
    sc: Scenario,
    out_dir: Path,
    *,
    source: str = "scenario",
    force: bool = False,
    workers: int = 1,
    progress: bool = False,
) -> SimSummary:
    t_start = time.perf_counter()
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())) and not force:
        raise CvslamError(f"{out_dir}: already exists and is not empty (use --force to replace it)")
    check_writable([out_dir])  # before the work: a read-only folder, -o under a file
    world = build_world(sc)
    vehicles = _vehicles(sc, world, source)
    landmarks = _landmark_world(sc, world) if sc.mode == "landmarks" else None
    render_state = {"world": world, "scenario": sc}
    with atomic_dir(out_dir) as tmp:
        out = SimLayout(tmp)
        out.truth_dir.mkdir()
        summaries = {
            v.names.vehicle: _write_vehicle(out, sc, v, landmarks, workers, progress, render_state)
            for v in vehicles
        }
        _write_world(out, world)
        if landmarks is not None:
            write_text_atomic(out.true_landmarks, _landmarks_csv(landmarks))
        write_text_atomic(out.scenario, yaml.safe_dump(dump_scenario(sc), sort_keys=False))
    return SimSummary(out_dir, summaries, time.perf_counter() - t_start)
