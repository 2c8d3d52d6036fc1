"""Scenario files for `cvslam simulate` (YAML, e.g. `configs/scenarios/uav2_paper.yaml`).

Loaded into frozen dataclasses with the same checked loader as the config (unknown key,
wrong type, out-of-range value -> one line naming the file and key path). The world and
sensor sub-sections are the simulator's own parameter dataclasses (`TerrainSpec`,
`YardSpec`, `ImuNoise`, `OdometryNoise`), so every documented parameter is a scenario key.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

from cvslam_cli.config import (
    CONFIG_DIR,
    build_dataclass,
    deep_merge,
    opt,
    parse_override,
    to_dict,
)
from cvslam_cli.errors import ConfigError
from cvslam_cli.io.textfiles import read_yaml_mapping
from cvslam_cli.sim.imu import ImuNoise
from cvslam_cli.sim.odometry import OdometryNoise
from cvslam_cli.sim.terrain import TerrainSpec
from cvslam_cli.sim.yard import YardSpec

SCENARIO_DIR = CONFIG_DIR / "scenarios"  # package data (cvslam_cli/configs/scenarios)


@dataclass(frozen=True)
class StereoRigSpec:
    """The simulated stereo camera of one vehicle.

    `mount`: "down" (optical axis along body +z; image up = vehicle forward) or "forward"
    (optical axis along body +x), then tilted by `tilt_deg` about the camera x axis
    (positive: the view turns towards the body's down/back side). The left camera sits at
    `lever_arm_m` in the body frame; the right one `baseline_m` along the left camera's x.
    A non-rectified rig (`rectified: false`) turns the right camera by
    `right_rotation_deg` (roll, pitch, yaw about the left camera axes) and gives both
    cameras the radial-tangential `distortion` (k1, k2, p1, p2, k3).
    """

    mount: Literal["down", "forward"] = "down"
    tilt_deg: float = opt(0.0, lo=-89.0, hi=89.0)
    width: int = opt(752, lo=16)
    height: int = opt(480, lo=16)
    fx: float = opt(450.0, lo=1.0)
    fy: float = opt(450.0, lo=1.0)
    cx: float = 375.5
    cy: float = 239.5
    baseline_m: float = opt(1.0, lo=0.0, lo_open=True)
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.1)
    rectified: bool = True
    right_rotation_deg: tuple[float, float, float] = (0.4, -0.8, 0.3)
    distortion: tuple[float, ...] = (-0.25, 0.07, 0.0002, -0.0001, 0.0)
    rate_hz: float = opt(10.0, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class SimVehicle:
    """One vehicle: its path, sensors and when it records.

    The path is a smooth curve through `waypoints_nav_m` (north, east, down in metres; for a
    ground robot down is ignored and the robot drives on the ground) flown at `speed_m_s`,
    a loop returning to its start when `closed`. The vehicle records from `start_s` to the
    scenario's end; a closed path is flown lap after lap, an open one is not repeated
    (the scenario's duration must fit in it).
    """

    kind: Literal["uav", "ugv"] = "uav"
    waypoints_nav_m: tuple[tuple[float, ...], ...] = ()
    closed: bool = False
    speed_m_s: float = opt(10.0, lo=0.0, lo_open=True)
    start_s: float = opt(0.0, lo=0.0)
    imu_rate_hz: float = opt(200.0, lo=0.0, lo_open=True)
    imu: ImuNoise = opt(ImuNoise())
    odometry_rate_hz: float = opt(50.0, lo=0.0, lo_open=True)
    odometry: OdometryNoise = opt(OdometryNoise())
    camera: StereoRigSpec = opt(StereoRigSpec())
    ground_truth_at: Literal["camera", "imu"] = "camera"


@dataclass(frozen=True)
class Photometry:
    """Per-frame exposure (gain ~ N(1, gain_sigma), offset ~ N(0, offset_sigma), both
    applied to radiance in [0, 1]) and sensor noise in grey levels."""

    gain_sigma: float = opt(0.06, lo=0.0)
    offset_sigma: float = opt(0.02, lo=0.0)
    noise_sigma_dn: float = opt(2.0, lo=0.0)


@dataclass(frozen=True)
class LandmarkMode:
    """`mode: landmarks`: point landmarks instead of images.

    `density_per_100m2` landmarks are scattered on the visible surfaces; every frame observes
    those inside both images within `max_range_m`, each missed with `miss_probability`,
    with Gaussian pixel noise `pixel_noise_px` (independently in both images) and a
    per-observation descriptor perturbation `descriptor_noise` (grey levels); a fraction
    `outlier_fraction` of the matches of each frame are wrong (random pixels and a random
    descriptor, landmark id -2). Such matches are never near a landmark with a descriptor
    like theirs, so the filter's association never takes them; the wrong matches that do
    reach it are look-alikes (repeated texture): `lookalike_fraction` of the matches of each
    frame imitate a landmark in view (its descriptor, perturbed like a true observation's,
    and its disparity) at a pixel up to `lookalike_offset_px` from its own, landmark id -2.
    `observer_offset_m`: each vehicle sees each landmark displaced by an offset of its own,
    fixed over the mission (Gaussian, this standard deviation per nav axis; 0: none), as the
    images' keypoints of one point land on different parts of its texture from different
    viewpoints: an error common to all of a vehicle's observations of a landmark, which its
    own track cannot average away and by which another vehicle's observations disagree.
    """

    density_per_100m2: float = opt(2.0, lo=0.0, lo_open=True)
    pixel_noise_px: float = opt(0.5, lo=0.0)
    miss_probability: float = opt(0.1, lo=0.0, hi=1.0)
    outlier_fraction: float = opt(0.03, lo=0.0, hi=1.0)
    lookalike_fraction: float = opt(0.0, lo=0.0, hi=0.9)
    lookalike_offset_px: float = opt(5.0, lo=0.0)
    observer_offset_m: float = opt(0.0, lo=0.0)
    descriptor_noise: float = opt(6.0, lo=0.0)
    max_range_m: float = opt(250.0, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class Outputs:
    """Optional ground-truth products. `depth`: per-pixel depth of every left image
    (`truth/<vehicle>_depth.npz`, float16 metres, NaN where nothing is seen)."""

    depth: bool = False


@dataclass(frozen=True)
class Scenario:
    name: str = "scenario"
    mode: Literal["images", "landmarks"] = "images"
    duration_s: float = opt(60.0, lo=0.0, lo_open=True)
    seed: int = opt(0, lo=0)
    world: Literal["terrain", "yard"] = "terrain"
    terrain: TerrainSpec = opt(TerrainSpec())
    yard: YardSpec = opt(YardSpec())
    photometry: Photometry = opt(Photometry())
    landmarks: LandmarkMode = opt(LandmarkMode())
    outputs: Outputs = opt(Outputs())
    vehicles: dict[str, SimVehicle] = opt({})


def resolve_scenario_path(path: Path) -> Path:
    """A scenario file, or the name of one in configs/scenarios (`uav2_paper`)."""
    if path.exists() or path.suffix:
        return path
    named = SCENARIO_DIR / f"{path}.yaml"
    return named if named.exists() else path


def load_scenario(
    path: Path,
    overrides: Sequence[str] = (),
    *,
    seed: int | None = None,
    duration_s: float | None = None,
) -> Scenario:
    """Read and check a scenario file; `overrides` are `key.path=value` strings."""
    raw = read_yaml_mapping(path, "a scenario file (YAML)", ConfigError, empty_ok=True)
    build_dataclass(Scenario, raw, "", str(path))  # errors name the file
    for text in overrides:
        parts, value = parse_override(text)
        patch: Any = value
        for p in reversed(parts):
            patch = {p: patch}
        build_dataclass(Scenario, patch, "", f"--set {text}")
        raw = deep_merge(raw, patch)
    scenario: Scenario = build_dataclass(Scenario, raw, "", str(path))
    if seed is not None:
        if seed < 0:
            raise ConfigError(f"--seed: expected an integer >= 0, got {seed}")
        scenario = replace(scenario, seed=seed)
    if duration_s is not None:
        scenario = stretch(scenario, duration_s)
    check_scenario(scenario, str(path))
    return scenario


def stretch(sc: Scenario, duration_s: float) -> Scenario:
    """The same mission over `duration_s`: every vehicle flies the same path, with speeds and
    start times scaled by the ratio of durations (sensor rates unchanged), so events such as
    loop closures and cross-vehicle overlaps keep their order and relative timing."""
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError(
            f"--duration: expected a finite, positive number of seconds, got {duration_s:g}"
        )
    k = sc.duration_s / duration_s
    vehicles = {
        name: replace(v, speed_m_s=v.speed_m_s * k, start_s=v.start_s / k)
        for name, v in sc.vehicles.items()
    }
    return replace(sc, duration_s=duration_s, vehicles=vehicles)


def check_scenario(sc: Scenario, source: str) -> None:
    """Checks that need more than one key at a time."""
    if not sc.vehicles:
        raise ConfigError(f"{source}: vehicles: expected at least one vehicle")
    for name, v in sc.vehicles.items():
        key = f"{source}: vehicles.{name}"
        if len(v.waypoints_nav_m) < 2:
            raise ConfigError(
                f"{key}.waypoints_nav_m: expected at least 2 waypoints, got "
                f"{len(v.waypoints_nav_m)}"
            )
        for i, wp in enumerate(v.waypoints_nav_m):
            if len(wp) != 3:
                raise ConfigError(
                    f"{key}.waypoints_nav_m[{i}]: expected [north, east, down] "
                    f"metres, got {list(wp)}"
                )
        if v.start_s >= sc.duration_s:
            raise ConfigError(
                f"{key}.start_s: {v.start_s:g} s is not before the end of the "
                f"scenario ({sc.duration_s:g} s)"
            )
        if v.kind == "ugv" and sc.world != "yard" and v.camera.mount == "down":
            raise ConfigError(f"{key}.camera.mount: a ground robot needs a forward camera")
        if v.camera.rate_hz > v.imu_rate_hz and v.kind == "uav":
            raise ConfigError(
                f"{key}.camera.rate_hz: {v.camera.rate_hz:g} Hz is faster than "
                f"the IMU ({v.imu_rate_hz:g} Hz)"
            )


def dump_scenario(sc: Scenario) -> dict[str, Any]:
    return to_dict(sc)
