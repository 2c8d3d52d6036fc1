"""Configuration: YAML files loaded into frozen dataclasses, validated at the boundary.

Sources, lowest precedence first: the dataclass defaults (mirrored, with a comment per key,
in `cvslam_cli/configs/default.yaml`: `configs/` of the repository), then each `--config
FILE`, then each `--set key.path=value`.
Each source is checked on its own so that an error names the file (or the `--set` option)
and the key path at fault, plus what was expected:

    configs/my.yaml: logs.stereo_pair_tolerance_ms: expected a number >= 0, got -1

Entries of `logs.vehicles` are deep-merged over `logs.vehicle_defaults`, so a vehicle only
states what differs from the defaults (usually a topic or two).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import importlib.resources
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from cvslam_cli.errors import ConfigError
from cvslam_cli.io.textfiles import read_yaml_mapping

IDENTITY_4X4: tuple[float, ...] = tuple(1.0 if i % 5 == 0 else 0.0 for i in range(16))
# The shipped configs and scenarios (package data; `configs` in the repository root is a link
# to it). An installed package is a folder, so its resources are plain paths.
CONFIG_DIR = Path(str(importlib.resources.files("cvslam_cli") / "configs"))
DEFAULT_CONFIG_PATH = CONFIG_DIR / "default.yaml"


def opt(
    default: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    at_most: str | None = None,
) -> Any:
    """A dataclass field with an optional numeric range (`lo`, `hi`; `lo_open`: lo excluded);
    `at_most`: the sibling field this one may not exceed (the low end of a pair, e.g.
    `layers_min` of `layers_max`), checked on the resolved config."""
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "at_most": at_most}
    if isinstance(default, (dict, list, tuple)) or dataclasses.is_dataclass(default):
        return field(default_factory=lambda: copy.deepcopy(default), metadata=meta)
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------- schema


@dataclass(frozen=True)
class TopicMap:
    """Topic names of one vehicle; `{vehicle}` is replaced by the vehicle's name."""

    left_image: str = "/{vehicle}/stereo/left/image_raw"
    right_image: str = "/{vehicle}/stereo/right/image_raw"
    left_info: str = "/{vehicle}/stereo/left/camera_info"
    right_info: str = "/{vehicle}/stereo/right/camera_info"
    imu: str = "/{vehicle}/imu"
    odom: str = "/{vehicle}/odom"
    ground_truth: str = "/{vehicle}/ground_truth/pose"

    def resolve(self, vehicle: str) -> TopicMap:
        return TopicMap(
            **{k: v.replace("{vehicle}", vehicle) for k, v in dataclasses.asdict(self).items()}
        )


@dataclass(frozen=True)
class CameraConfig:
    """Calibration of one camera, used when the log has no CameraInfo for it.

    `T_body_cam` is the 4x4 homogeneous transform (16 numbers, row-major) mapping camera
    optical-frame coordinates to body coordinates. `fx <= 0` means "not configured".
    """

    width: int = opt(0, lo=0)
    height: int = opt(0, lo=0)
    fx: float = 0.0
    fy: float = 0.0
    cx: float = 0.0
    cy: float = 0.0
    distortion_model: Literal["plumb_bob", "radtan", "equidistant", "none"] = "none"
    distortion: tuple[float, ...] = ()
    T_body_cam: tuple[float, ...] = IDENTITY_4X4

    @property
    def configured(self) -> bool:
        return self.fx != 0.0


@dataclass(frozen=True)
class RigConfig:
    """Stereo rig of one vehicle: fallback calibration and TF frame names.
    `camera_time_offset_ns` is added to image stamps to put them on the IMU's clock (Kalibr's
    `timeshift_cam_imu`: t_imu = t_cam + shift)."""

    body_frame: str = "{vehicle}/base_link"
    left: CameraConfig = opt(CameraConfig())
    right: CameraConfig = opt(CameraConfig())
    camera_time_offset_ns: int = 0


@dataclass(frozen=True)
class VehicleConfig:
    """One vehicle. `log`: the log file (or rosbag2 folder) holding this vehicle's topics,
    read with its topic names as they are (`NAME=PATH` on the command line; in YAML also the
    shorthand `logs.vehicles: {NAME: PATH}`); empty: looked for in every log given.
    `ground_truth_frame`: the world frame of its ground truth (topic or `--gt` file), converted
    to the nav frame once where it is read (geometry/nav_frames.py)."""

    kind: Literal["uav", "ugv"] = "uav"
    topics: TopicMap = opt(TopicMap())
    rig: RigConfig = opt(RigConfig())
    log: str = ""
    ground_truth_frame: Literal["ned", "enu", "nwu", "camera"] = "ned"


@dataclass(frozen=True)
class LogsConfig:
    """How logs are read and split into vehicles."""

    vehicles: dict[str, VehicleConfig] = opt({})
    vehicle_defaults: VehicleConfig = opt(VehicleConfig())
    tf_static_topic: str = "/tf_static"
    stereo_pair_tolerance_ms: float = opt(2.0, lo=0.0)
    reorder_window_ms: float = opt(100.0, lo=0.0)
    gap_factor: float = opt(3.0, lo=1.0, lo_open=True)


@dataclass(frozen=True)
class SiftConfig:
    """OpenCV SIFT parameters (the fixed detector, and the starting point of the adaptive one)."""

    n_octave_layers: int = opt(3, lo=1, hi=10)
    contrast_threshold: float = opt(0.04, lo=0.0, lo_open=True)
    edge_threshold: float = opt(10.0, lo=1.0)
    sigma: float = opt(1.6, lo=0.5)
    half_resolution_base: bool = True


@dataclass(frozen=True)
class AdaptiveSiftConfig:
    """Adaptive SIFT: scale step and contrast threshold chosen per image from the energy of
    its difference-of-Gaussian response, keypoint count kept inside [features_min,
    features_max] (derivation in cvslam_cli/features/sift.py)."""

    enabled: bool = True
    dog_rms_ref: float = opt(0.01, lo=0.0, lo_open=True)
    contrast_per_rms: float = opt(2.0, lo=0.0, lo_open=True)
    layers_min: int = opt(2, lo=1, hi=10, at_most="layers_max")
    layers_max: int = opt(6, lo=1, hi=10)
    contrast_min: float = opt(0.002, lo=0.0, lo_open=True, at_most="contrast_max")
    contrast_max: float = opt(0.08, lo=0.0, lo_open=True)
    features_min: int = opt(150, lo=0, at_most="features_max")
    features_max: int = opt(1200, lo=1)
    retry_factor: float = opt(0.5, lo=0.0, hi=1.0, lo_open=True)


@dataclass(frozen=True)
class StereoMatchConfig:
    """Stereo-constrained matching (paper eq. 20-34) and triangulation."""

    z_min_m: float = opt(0.0, lo=0.0)
    max_range_m: float = opt(0.0, lo=0.0)
    vertical_tolerance_px: float = opt(1.5, lo=0.0, lo_open=True)
    dist_ratio: float = opt(0.7, lo=0.0, hi=1.0, lo_open=True)
    left_right_check: bool = True
    pixel_sigma_px: float = opt(0.3, lo=0.0, lo_open=True)
    calibrate_disparity_offset: bool = False


@dataclass(frozen=True)
class ExtractConfig:
    sift: SiftConfig = opt(SiftConfig())
    adaptive: AdaptiveSiftConfig = opt(AdaptiveSiftConfig())
    stereo: StereoMatchConfig = opt(StereoMatchConfig())


@dataclass(frozen=True)
class HinfConfig:
    """Nonlinear H-infinity filter (DESIGN.md section 2): Q_hat = c_w^2 Q, R_hat = c_v^2 R,
    bound gamma on the vehicle states, the observing vehicle's or all states."""

    gamma: float = opt(30.0, lo=0.0, lo_open=True)
    c_w: float = opt(1.0, lo=1.0)
    c_v: float = opt(1.0, lo=1.0)
    bound: Literal["vehicle", "observer", "all"] = "observer"
    gamma_margin: float = opt(10.0, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class MotionConfig:
    """Motion models and their process noise."""

    model: Literal["auto", "ins", "odometry", "constant_velocity"] = "auto"
    fallback_constant_velocity: bool = True
    imu_biases: bool = True
    accel_noise_density: float = opt(2.0e-3, lo=0.0, lo_open=True)
    gyro_noise_density: float = opt(1.6968e-4, lo=0.0, lo_open=True)
    accel_random_walk: float = opt(3.0e-3, lo=0.0)
    gyro_random_walk: float = opt(1.9393e-5, lo=0.0)
    odometry_speed_noise_density: float = opt(0.05, lo=0.0, lo_open=True)
    odometry_yaw_rate_noise_density: float = opt(0.01, lo=0.0, lo_open=True)
    cv_accel_noise_density: float = opt(2.0, lo=0.0, lo_open=True)
    cv_angular_accel_noise_density: float = opt(0.5, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class KnownPoseConfig:
    """A vehicle's initial pose given in the config (nav frame NED, m; ZYX Euler angles,
    rad; nav-frame velocity, m/s), used instead of `source` for that vehicle."""

    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    euler_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class UnknownPoseConfig:
    """A vehicle whose initial pose is unknown: it starts from a rough prior, the `source`
    pose moved by `offset_m` (nav frame) and turned by `yaw_offset_rad`, with standard
    deviations `position_sigma_m` (each axis) and `yaw_sigma_rad`, and is localised in the
    shared map once it sees mapped landmarks."""

    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_offset_rad: float = 0.0
    position_sigma_m: float = opt(20.0, lo=0.0, lo_open=True)
    yaw_sigma_rad: float = opt(0.5, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class InitialConfig:
    """Initial vehicle state and its uncertainty (standard deviations); vehicles with an
    unknown initial pose and how they are localised in the shared map."""

    source: Literal["ground_truth", "origin"] = "ground_truth"
    position_sigma_m: float = opt(0.1, lo=0.0, lo_open=True)
    attitude_sigma_rad: float = opt(0.005, lo=0.0, lo_open=True)
    velocity_sigma_m_s: float = opt(0.1, lo=0.0, lo_open=True)
    angular_rate_sigma_rad_s: float = opt(0.05, lo=0.0, lo_open=True)
    accel_bias_sigma_m_s2: float = opt(0.05, lo=0.0, lo_open=True)
    gyro_bias_sigma_rad_s: float = opt(2.0e-3, lo=0.0, lo_open=True)
    poses: dict[str, KnownPoseConfig] = opt({})
    unknown: dict[str, UnknownPoseConfig] = opt({})
    localise_min_inliers: int = opt(12, lo=4)
    localise_reprojection_px: float = opt(2.0, lo=0.0, lo_open=True)
    localise_prior_probability: float = opt(0.999, lo=0.5, hi=1.0, lo_open=True)
    localise_confirm_frames: int = opt(3, lo=1)


@dataclass(frozen=True)
class AssociationConfig:
    """Data association of stereo matches with mapped landmarks."""

    pixel_sigma_px: Literal["auto"] | float = opt("auto", lo=0.0, lo_open=True)
    gate_probability: float = opt(0.999, lo=0.5, hi=1.0, lo_open=True)
    consistency_probability: float = opt(0.999, lo=0.5, hi=1.0, lo_open=True)
    descriptor_ratio: float = opt(0.8, lo=0.0, hi=1.0, lo_open=True)
    other_vehicle_descriptor_ratio: float = opt(0.7, lo=0.0, hi=1.0, lo_open=True)
    other_vehicle_ratio_over_frame: bool = True
    other_vehicle_pixel_sigma_px: float = opt(0.0, lo=0.0)
    other_vehicle_max_distance_ratio: float = opt(4.0, lo=0.0)
    other_vehicle_lookalikes_per_mpx: Literal["auto"] | float = opt("auto", lo=0.0)
    max_descriptor_distance: float = opt(350.0, lo=0.0, lo_open=True)
    octave_bearing_variance: Literal["auto"] | tuple[float, ...] = opt("auto", lo=0.0, lo_open=True)
    iterate_sigma_ratio: float = opt(0.05, lo=0.0)
    iterate_bearing_sigma_rad: float = opt(0.0, lo=0.0)
    max_update_iterations: int = opt(5, lo=1)


@dataclass(frozen=True)
class MapConfig:
    """Landmarks in the filter state and their management."""

    max_landmarks: int = opt(150, lo=1)
    landmarks_per_added_vehicle: int = opt(100, lo=0)
    max_landmarks_total: int = opt(400, lo=1)
    max_updates_per_frame: Literal["auto"] | int = opt("auto", lo=1)
    target_tracked: Literal["auto"] | int = opt("auto", lo=0)
    max_new_per_frame: int = opt(15, lo=0)
    max_new_depth_sigma_ratio: float = opt(0.25, lo=0.0, lo_open=True)
    new_landmark_priority: Literal["previous_frame", "current_frame"] = "previous_frame"
    landmark_coordinates: Literal["auto", "cartesian", "inverse_depth"] = "auto"
    anchor_span_s: float = opt(0.0, lo=0.0)
    reanchor_max_landmarks: int = opt(8, lo=0)
    max_view_angle_deg: float = opt(80.0, lo=0.0, hi=180.0, lo_open=True)
    others_tracking_s: float = opt(0.0, lo=0.0)
    loop_closure_gap_s: float = opt(20.0, lo=0.0, lo_open=True)
    loop_closure_min_landmarks: int = opt(3, lo=1)
    event_merge_s: float = opt(5.0, lo=0.0)
    joint_initialisation: bool = True
    joint_init_window_s: float = opt(0.2, lo=0.0)
    reactivation: bool = True
    reactivation_inflation: float = opt(16.0, lo=1.0)
    prior_map_inflation: float = opt(16.0, lo=1.0)
    refined_prior_map_inflation: float = opt(1.0, lo=1.0)
    reactivation_min_absence_s: float = opt(20.0, lo=0.0)
    reactivation_min_landmarks: int = opt(3, lo=1)
    max_reactivated_per_frame: int = opt(15, lo=1)


@dataclass(frozen=True)
class WindowConfig:
    """The sliding window of pose clones and the feature tracks that update them
    (estimation/window_update.py)."""

    clones: int = opt(0, lo=0)
    max_tracks: int = opt(60, lo=1)
    gate_probability: float = opt(0.95, lo=0.5, hi=1.0, lo_open=True)


@dataclass(frozen=True)
class DivergenceConfig:
    """A vehicle's filter has diverged when its median NIS per measurement over the last
    `window` updated frames exceeds `nis_per_dof_max` (1 is nominal)."""

    window: int = opt(20, lo=1)
    nis_per_dof_max: float = opt(10.0, lo=1.0, lo_open=True)


@dataclass(frozen=True)
class RelocalisationConfig:
    """A vehicle whose pose the map contradicts (estimation/relocalisation.py): its frame is
    located in the map by appearance (descriptors, PnP) every `check_interval_s`, and at
    every frame that tracked too few of the landmarks in view; a pose that the filter's
    covariance rejects at `gate_probability` (6 dof) in `fuse.initial.localise_confirm_frames`
    consecutive frames, or a filter whose innovations say it lost the map
    (`fuse.divergence`), makes the vehicle lost: its position, velocity and attitude are
    forgotten (standard deviations `position_sigma_m`, `velocity_sigma_m_s`,
    `attitude_sigma_rad`), so are the landmarks it alone mapped since it last tracked the
    map, and it is found again in the map as for an unknown initial pose. After
    `max_per_vehicle` losses of one vehicle the next is a divergence. A vehicle whose
    position standard deviation exceeds `uncertain_sigma_ratio` times the median depth of its
    frame is checked at every frame, and an agreeing pose taken at once instead of its
    windows' associations. `enabled` false: no check, and a lost map is a divergence."""

    enabled: bool = True
    check_interval_s: float = opt(1.0, lo=0.0, lo_open=True)
    gate_probability: float = opt(0.999999, lo=0.5, hi=1.0, lo_open=True)
    position_sigma_m: float = opt(20.0, lo=0.0, lo_open=True)
    velocity_sigma_m_s: float = opt(5.0, lo=0.0, lo_open=True)
    attitude_sigma_rad: float = opt(0.2, lo=0.0, lo_open=True)
    max_per_vehicle: int = opt(5, lo=0)
    uncertain_sigma_ratio: float = opt(0.1, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class CalibrationConfig:
    """The stereo rigs' calibration, estimated (estimation/rig_calibration.py):
    `estimate_right_cx` runs a calibration pass of the filter with each vehicle's right
    principal point u0 a state of its block (prior standard deviation `right_cx_sigma_px`),
    then the run with each rig corrected by its estimate."""

    estimate_right_cx: bool = False
    right_cx_sigma_px: float = opt(1.0, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class FuseConfig:
    """`cvslam fuse`. `prior_map`: a map saved by an earlier run to start from (its run
    directory, whose `fuse/map.npz` is read, or a `map.npz`; empty: none)."""

    filter: Literal["hinf", "ekf"] = "hinf"
    observability_constrained: Literal["auto"] | bool = "auto"
    prior_map: str = ""
    hinf: HinfConfig = opt(HinfConfig())
    motion: MotionConfig = opt(MotionConfig())
    initial: InitialConfig = opt(InitialConfig())
    association: AssociationConfig = opt(AssociationConfig())
    map: MapConfig = opt(MapConfig())
    window: WindowConfig = opt(WindowConfig())
    divergence: DivergenceConfig = opt(DivergenceConfig())
    relocalisation: RelocalisationConfig = opt(RelocalisationConfig())
    calibration: CalibrationConfig = opt(CalibrationConfig())


@dataclass(frozen=True)
class GroundConfig:
    """The ground surface images are projected on: a plane fitted to the mapped landmarks
    (RANSAC), replaced by a plane of its own in each `region_size_m` square whose landmarks
    lie a median distance of more than `max_residual_m` off the global plane. Thresholds of
    0 scale with the scene (mosaic/ground.py)."""

    inlier_threshold_m: float = opt(0.0, lo=0.0)
    max_tilt_deg: float = opt(30.0, lo=0.0, hi=89.0, lo_open=True)
    region_size_m: float = opt(35.0, lo=0.0, lo_open=True)
    min_region_points: int = opt(20, lo=3)
    max_residual_m: float = opt(0.0, lo=0.0)
    max_landmark_std_m: float = opt(5.0, lo=0.0, lo_open=True)


@dataclass(frozen=True)
class MosaicConfig:
    source: Literal["fused", "deadreckoning", "groundtruth"] = "fused"
    fuse_dir: str = "fuse"
    every_nth: int = opt(1, lo=1)
    gsd_m: float = opt(0.0, lo=0.0)
    blend: Literal["feather", "multiband"] = "feather"
    feather_sharpness: float = opt(0.02, lo=0.0, lo_open=True)
    multiband_bands: int = opt(5, lo=1, hi=10)
    border_px: int = opt(2, lo=0)
    max_range_m: float = opt(0.0, lo=0.0)
    min_depression_deg: float = opt(5.0, lo=0.0, hi=90.0)
    max_canvas_mpx: float = opt(64.0, lo=0.0, lo_open=True)
    auto_max_mpx: float = opt(16.0, lo=0.0, lo_open=True)
    overlay: bool = True
    ground: GroundConfig = opt(GroundConfig())


@dataclass(frozen=True)
class EvalConfig:
    """`cvslam eval`: alignment of estimates to the truth (none: the nav frame is known),
    timestamp association tolerance, RPE distances (empty: 10 % and 25 % of each vehicle's
    path), and the probability of the NEES consistency band."""

    align: Literal["none", "se3", "sim3"] = "none"
    max_time_diff_ms: float = opt(10.0, lo=0.0)
    rpe_delta_m: tuple[float, ...] = ()
    nees_band_probability: float = opt(0.95, lo=0.0, hi=1.0, lo_open=True)


@dataclass(frozen=True)
class ReassociationConfig:
    """`cvslam refine`'s re-association (refine/reassociation.py): rounds of associating
    every landmark in every keyframe (guided matching) and tracking the unmapped stereo
    matches, each followed by a solution; the first round's pixel gate, the later rounds'
    chi-square gate probability, the descriptor ratio test and largest distance, the
    tracks and their shortest length in keyframes, descriptors kept per point."""

    rounds: int = opt(2, lo=0)
    gate_px: float = opt(4.0, lo=0.0, lo_open=True)
    gate_probability: float = opt(0.999, lo=0.5, hi=0.999999, lo_open=True)
    descriptor_ratio: float = opt(0.8, lo=0.0, hi=1.0, lo_open=True)
    max_descriptor_distance: float = opt(350.0, lo=0.0, lo_open=True)
    tracks: bool = True
    min_track_keyframes: int = opt(3, lo=2)
    max_descriptors: int = opt(8, lo=1)


@dataclass(frozen=True)
class RefineConfig:
    """`cvslam refine`: the fuse folder refined (its trajectories, map and observations),
    keyframes (every n-th frame of each vehicle), the pixel noise of the reprojection
    factors (0: the features' own, extract.stereo.pixel_sigma_px or the simulator's pixel
    noise), the robust kernel and its threshold (in standard deviations), the standard
    deviation holding a ground robot's height, roll and pitch, Levenberg-Marquardt's limits
    and its elimination ordering, whether the landmarks' marginal covariances are
    computed (map std columns), and whether each rig's right-camera principal point u0 is
    estimated (prior standard deviation right_cx_sigma_px; refine/right_cx.py)."""

    source: Literal["fuse", "fuse_ekf", "fuse_single", "fuse_ekf_single"] = "fuse"
    every_nth: int = opt(1, lo=1)
    pixel_sigma_px: float = opt(0.0, lo=0.0)
    robust: Literal["huber", "cauchy", "none"] = "huber"
    robust_k: float = opt(1.345, lo=0.0, lo_open=True)
    planar_sigma: float = opt(0.001, lo=0.0, lo_open=True)
    max_iterations: int = opt(50, lo=1)
    relative_error_tol: float = opt(1e-6, lo=0.0)
    ordering: Literal["metis", "colamd"] = "metis"
    landmark_covariances: bool = True
    estimate_right_cx: bool = False
    right_cx_sigma_px: float = opt(1.0, lo=0.0, lo_open=True)
    reassociation: ReassociationConfig = opt(ReassociationConfig())


@dataclass(frozen=True)
class RunConfig:
    """`cvslam run`: the fuse runs made besides the cooperative NH-infinity one, for
    comparison (single: each vehicle alone; ekf: the EKF; ekf_single; refined: `cvslam
    refine` of the cooperative run), whether to make mosaics, and the dataset the run is of
    (metrics.csv; empty: the run directory's name)."""

    comparisons: tuple[Literal["single", "ekf", "ekf_single", "refined"], ...] = ("single", "ekf")
    mosaic: bool = True
    dataset: str = ""


@dataclass(frozen=True)
class GeoOrigin:
    """The nav frame's origin on the Earth (WGS 84): latitude and longitude (degrees; UTM
    covers -80 to 84 degrees of latitude), ellipsoidal height (m), and heading: the azimuth
    of the nav x axis ("north"), degrees clockwise from true north (0: the nav frame is true
    north-east-down). Every key is required (geometry/georef.py)."""

    lat_deg: float = field(metadata={"lo": -80.0, "hi": 84.0})
    lon_deg: float = field(metadata={"lo": -180.0, "hi": 180.0})
    alt_m: float = field(metadata={"lo": -12000.0, "hi": 100000.0})
    heading_deg: float = field(metadata={"lo": -360.0, "hi": 360.0})


@dataclass(frozen=True)
class GeoConfig:
    """Where the nav frame is on the Earth, for georeferenced outputs (mosaics in UTM);
    None: unknown (the mosaics get a local engineering CRS in metres)."""

    origin: GeoOrigin | None = None


@dataclass(frozen=True)
class Config:
    logs: LogsConfig = opt(LogsConfig())
    extract: ExtractConfig = opt(ExtractConfig())
    fuse: FuseConfig = opt(FuseConfig())
    mosaic: MosaicConfig = opt(MosaicConfig())
    eval: EvalConfig = opt(EvalConfig())
    refine: RefineConfig = opt(RefineConfig())
    run: RunConfig = opt(RunConfig())
    geo: GeoConfig = opt(GeoConfig())


# --------------------------------------------------------------------------- building


def _type_name(tp: Any, meta: Mapping[str, Any] | None = None) -> str:
    """What a value of type `tp` is, in words; with a field's `meta`, a number's range."""
    origin = typing.get_origin(tp)
    if origin is Literal:
        args = typing.get_args(tp)
        return repr(args[0]) if len(args) == 1 else "one of " + ", ".join(repr(a) for a in args)
    if tp in (int, float):
        return (("a number" if tp is float else "an integer") + _range(meta or {})).rstrip()
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    if origin is tuple:
        args = typing.get_args(tp)
        variable = len(args) == 2 and args[1] is Ellipsis
        count = "" if variable else f"{len(args)} "
        each = _type_name(args[0]).removeprefix("a ").removeprefix("an ")
        return f"a list of {count}{each}s" + (_range(meta or {}) if variable else "")
    if origin is dict:
        return "a mapping"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return str(tp)


def _range(meta: Mapping[str, Any]) -> str:
    """A number field's range in words (" > 0", " >= 0 and <= 1"), "" without one."""
    lo, hi = meta.get("lo"), meta.get("hi")
    out = ""
    if lo is not None:
        out += f" {'>' if meta.get('lo_open') else '>='} {lo}"
    if hi is not None:
        out += f" <= {hi}" if lo is None else f" and <= {hi}"
    return out


def _fail(source: str, path: str, expected: str, got: Any) -> typing.NoReturn:
    shown = "nothing" if got is None else repr(got)
    if len(shown) > 60:
        shown = shown[:57] + "..."
    raise ConfigError(f"{source}: {path}: expected {expected}, got {shown}")


def _convert(tp: Any, raw: Any, path: str, source: str, meta: Mapping[str, Any]) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if raw is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return _convert(inner[0], raw, path, source, meta)
        for alternative in inner:  # e.g. Literal["auto"] | float: the first that fits
            try:
                return _convert(alternative, raw, path, source, meta)
            except ConfigError:
                pass
        _fail(source, path, " or ".join(_type_name(a, meta) for a in inner), raw)
    if dataclasses.is_dataclass(tp):
        if not isinstance(raw, Mapping):
            _fail(source, path, "a mapping", raw)
        return build_dataclass(tp, raw, path, source)
    if origin is Literal:
        if raw not in typing.get_args(tp):
            _fail(source, path, _type_name(tp), raw)
        return raw
    if origin is dict:
        if not isinstance(raw, Mapping):
            _fail(source, path, "a mapping", raw)
        _, val_tp = typing.get_args(tp)
        for k in raw:
            problem = file_name_problem(str(k))
            if problem is not None:  # the keys (vehicle names) become file names
                raise ConfigError(f"{source}: {path}.{k}: {problem}")
        return {str(k): _convert(val_tp, v, f"{path}.{k}", source, {}) for k, v in raw.items()}
    if origin is tuple:
        if not isinstance(raw, (list, tuple)):
            _fail(source, path, _type_name(tp), raw)
        args = typing.get_args(tp)
        variable = len(args) == 2 and args[1] is Ellipsis
        if not variable and len(raw) != len(args):
            _fail(source, path, _type_name(tp), raw)
        elems = [args[0]] * len(raw) if variable else list(args)
        return tuple(  # a list of numbers: each in the field's range
            _convert(e, v, f"{path}[{i}]", source, meta if variable else {})
            for i, (e, v) in enumerate(zip(elems, raw, strict=True))
        )
    if tp is bool:
        if not isinstance(raw, bool):
            _fail(source, path, "true or false", raw)
        return raw
    if tp is str:
        if not isinstance(raw, str):
            _fail(source, path, "a string", raw)
        return raw
    if tp in (int, float):
        lo, hi = meta.get("lo"), meta.get("hi")
        expected = _type_name(tp, meta)
        number = raw
        if tp is float and isinstance(raw, str) and _EXPONENT_NUMBER_RE.fullmatch(raw.strip()):
            number = float(raw)  # YAML 1.1 (PyYAML) reads 1e-9 as a string
        ok = isinstance(number, int) if tp is int else isinstance(number, (int, float))
        if not ok or isinstance(number, bool) or (tp is float and not math.isfinite(number)):
            _fail(source, path, expected.replace("a ", "a finite ", 1) if ok else expected, raw)
        value = tp(number)
        if (lo is not None and (value < lo or (meta.get("lo_open") and value == lo))) or (
            hi is not None and value > hi
        ):
            _fail(source, path, expected, raw)
        return value
    raise TypeError(f"config type {tp!r} at {path} is not supported")  # a bug in the schema


# A number in exponent notation without a decimal point ("1e-9", "2E+3"): a float in
# YAML 1.2 and in Python, a string to PyYAML's YAML 1.1 resolver.
_EXPONENT_NUMBER_RE = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


# The longest file name made of a name is `<name>_deadreckoning.tum.partial`; 255 bytes
# is the limit of the common file systems, so names stay well below it.
MAX_NAME_BYTES = 200
_FILE_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+-]*$")


def file_name_problem(name: str) -> str | None:
    """Why `name` (a vehicle's, which becomes part of file names) cannot be used in a file
    name: empty, a path separator or other character outside letters, digits and `_.+-`,
    or too long; None when it can."""
    if not _FILE_NAME_RE.match(name):
        return (
            f"the name {name[:60]!r} cannot be part of a file name (expected letters, digits "
            "and _ . + -, starting with a letter, digit or _)"
        )
    if len(name.encode()) > MAX_NAME_BYTES:
        return (
            f"the name is {len(name.encode())} bytes long, at most {MAX_NAME_BYTES} fit a file name"
        )
    return None


def build_dataclass(cls: type, raw: Mapping[str, Any], path: str, source: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in raw:
        if key not in fields:
            where = f"{path}.{key}" if path else str(key)
            raise ConfigError(
                f"{source}: {where}: unknown key (expected one of: {', '.join(fields)})"
            )
    kwargs = {}
    for name, f in fields.items():
        if name in raw:
            sub = f"{path}.{name}" if path else name
            kwargs[name] = _convert(hints[name], raw[name], sub, source, f.metadata)
    required = [
        n
        for n, f in fields.items()
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    missing = [n for n in required if n not in kwargs]
    if missing:  # a group whose keys go together (geo.origin): given whole or not at all
        raise ConfigError(
            f"{source}: {path or 'config'}: missing key(s) {', '.join(missing)} "
            f"(give all of {', '.join(required)})"
        )
    return cls(**kwargs)


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _expand_vehicles(raw: Mapping[str, Any]) -> dict[str, Any]:
    """Deep-merge each `logs.vehicles.<name>` over `logs.vehicle_defaults`."""
    logs = raw.get("logs")
    if not isinstance(logs, Mapping) or not isinstance(logs.get("vehicles"), Mapping):
        return dict(raw)
    defaults = logs.get("vehicle_defaults") or {}
    if not isinstance(defaults, Mapping):
        return dict(raw)
    vehicles = {
        name: deep_merge(defaults, v) if isinstance(v, Mapping) else v
        for name, v in _log_shorthand(logs["vehicles"]).items()
    }
    return {**raw, "logs": {**logs, "vehicles": vehicles}}


def _log_shorthand(vehicles: Mapping[str, Any]) -> dict[str, Any]:
    """`logs.vehicles: {robot1: path}` is `{robot1: {log: path}}`."""
    return {k: {"log": v} if isinstance(v, str) else v for k, v in vehicles.items()}


def _normalise(raw: Mapping[str, Any]) -> dict[str, Any]:
    """A source with the `logs.vehicles` shorthand expanded (before merging sources)."""
    logs = raw.get("logs")
    if isinstance(logs, Mapping) and isinstance(logs.get("vehicles"), Mapping):
        return {**raw, "logs": {**logs, "vehicles": _log_shorthand(logs["vehicles"])}}
    return dict(raw)


def to_dict(cfg: Any) -> Any:
    """Plain YAML-ready data (tuples as lists) of a config dataclass."""
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, Mapping):
        return {k: to_dict(v) for k, v in cfg.items()}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    return cfg


def parse_override(text: str) -> tuple[list[str], Any]:
    """`a.b.c=value` -> (['a','b','c'], value parsed as YAML)."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set {text}: expected key.path=value")
    parts = key.strip().split(".")
    if any(not p for p in parts):
        raise ConfigError(f"--set {text}: empty component in key path {key!r}")
    try:
        parsed = yaml.safe_load(value) if value.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"--set {text}: value is not valid YAML ({exc.problem})") from None
    return parts, parsed


def _nest(parts: list[str], value: Any) -> dict[str, Any]:
    out: Any = value
    for p in reversed(parts):
        out = {p: out}
    return out


CONFIG_FILE = "a config file"


def resolve_config_path(path: Path | str) -> Path:
    """A config file, or the name of one shipped in the package (`kitti`, `paper`:
    cvslam_cli/configs/NAME.yaml), so that an installed cvslam has them too."""
    path = Path(path)
    if path.exists() or path.suffix or len(path.parts) != 1:
        return path
    named = CONFIG_DIR / f"{path}.yaml"
    return named if named.exists() else path


def config_sources(
    files: typing.Sequence[Path | str] = (),
    overrides: typing.Sequence[str] = (),
    layers: typing.Sequence[tuple[str, dict[str, Any]]] = (),
) -> list[tuple[str, dict[str, Any]]]:
    """The sources of a config as (name for messages, mapping), lowest precedence first:
    the config files, `layers` (e.g. a Kalibr calibration), the `key.path=value` overrides."""
    paths = [resolve_config_path(f) for f in files]
    sources: list[tuple[str, dict[str, Any]]] = [
        (str(f), read_yaml_mapping(f, CONFIG_FILE, ConfigError, empty_ok=True)) for f in paths
    ]
    sources.extend(layers)
    for text in overrides:
        parts, value = parse_override(text)
        sources.append((f"--set {text}", _nest(parts, value)))
    return sources


def load_config(
    files: typing.Sequence[Path | str] = (),
    overrides: typing.Sequence[str] = (),
    layers: typing.Sequence[tuple[str, dict[str, Any]]] = (),
) -> Config:
    """Build the resolved config from config files, then `layers` ((name for messages,
    mapping), e.g. a Kalibr calibration), then `key.path=value` overrides."""
    return config_from_sources(config_sources(files, overrides, layers))


def config_from_sources(sources: typing.Sequence[tuple[str, dict[str, Any]]]) -> Config:
    """The resolved config of `sources` (`config_sources`), each checked on its own."""
    merged: dict[str, Any] = {}
    for name, raw in sources:
        raw = _normalise(raw)
        # validate each source alone, so that an error names it
        build_dataclass(Config, _expand_vehicles(raw), "", name)
        merged = deep_merge(merged, raw)
    merged = _expand_vehicles(merged)
    cfg = build_dataclass(Config, merged, "", "config")
    _check_pairs(cfg, "", [(name, _expand_vehicles(raw)) for name, raw in sources])
    return cfg


def value_sources(sources: typing.Sequence[tuple[str, dict[str, Any]]]) -> dict[str, str]:
    """The source (its name in `sources`) that set each leaf key (dotted path) last; keys
    no source sets are the defaults' (a `logs.vehicles.NAME` key also comes from
    `logs.vehicle_defaults`)."""
    out: dict[str, str] = {}

    def walk(node: Any, path: str, name: str) -> None:
        if isinstance(node, Mapping) and node:
            for k, v in node.items():
                walk(v, f"{path}.{k}" if path else str(k), name)
        else:
            out[path] = name

    for name, raw in sources:
        walk(_normalise(raw), "", name)
    return out


def schema_keys(cls: type = Config, path: str = "") -> list[str]:
    """Every key path of a config dataclass, sections and leaves (mappings such as
    `logs.vehicles` are leaves: their keys are names)."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        sub = f"{path}.{f.name}" if path else f.name
        out.append(sub)
        if dataclasses.is_dataclass(hints[f.name]):
            out.extend(schema_keys(hints[f.name], sub))
    return out


def nearest_key(key: str, candidates: typing.Iterable[str]) -> str | None:
    """The candidate closest to `key` (a misspelt key), or None when none is close."""
    close = difflib.get_close_matches(key, list(candidates), n=1, cutoff=0.6)
    return close[0] if close else None


def config_problems(raw: Mapping[str, Any], source: str) -> list[str]:
    """Every problem of one config source (a file's mapping), one line each naming the
    source and the key: an unknown key with the nearest valid one, a wrong type or range
    (the checks `load_config` makes); then, when each key is right, what loading it alone
    says (e.g. a pair out of order). Empty: it loads."""
    problems: list[str] = []
    _collect_problems(Config, _normalise(raw), "", source, problems)
    if not problems:
        try:
            config_from_sources([(source, dict(raw))])
        except ConfigError as exc:
            problems.append(str(exc))
    return problems


def _collect_problems(
    cls: type, raw: Mapping[str, Any], path: str, source: str, out: list[str]
) -> None:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key, value in raw.items():
        sub = f"{path}.{key}" if path else str(key)
        if key not in fields:
            out.append(f"{source}: {sub}: unknown key ({_suggestion(cls, str(key), path)})")
            continue
        tp = hints[key]
        entry_tp = typing.get_args(tp)[1] if typing.get_origin(tp) is dict else None
        if dataclasses.is_dataclass(tp) and isinstance(value, Mapping):
            _collect_problems(tp, value, sub, source, out)
        elif dataclasses.is_dataclass(entry_tp) and isinstance(value, Mapping):
            for name, entry in value.items():
                problem = file_name_problem(str(name))
                if problem is not None:
                    out.append(f"{source}: {sub}.{name}: {problem}")
                elif isinstance(entry, Mapping):
                    _collect_problems(entry_tp, entry, f"{sub}.{name}", source, out)
                else:
                    out.append(f"{source}: {sub}.{name}: expected a mapping, got {entry!r}")
        else:
            try:
                _convert(tp, value, sub, source, fields[key].metadata)
            except ConfigError as exc:
                out.append(str(exc))


def _suggestion(cls: type, key: str, path: str) -> str:
    """'did you mean X?' for an unknown key: a sibling spelt alike, or a key of that name
    elsewhere in the section; else the keys expected there."""
    fields = [f.name for f in dataclasses.fields(cls)]
    near = nearest_key(key, fields)
    if near is not None:
        return f"did you mean {path + '.' if path else ''}{near}?"
    top = path.split(".")[0]
    elsewhere = [k for k in schema_keys() if k.split(".")[-1] == key and k.startswith(top)]
    if elsewhere:
        return f"did you mean {elsewhere[0]}?"
    return f"expected one of: {', '.join(fields)}"


def _check_pairs(node: Any, path: str, sources: list[tuple[str, dict[str, Any]]]) -> None:
    """Every `at_most` pair of the resolved config in order; ConfigError naming the sources
    that set either key (or the defaults) and both values."""
    if isinstance(node, Mapping):
        for k, v in node.items():
            _check_pairs(v, f"{path}.{k}", sources)
        return
    if not dataclasses.is_dataclass(node):
        return
    for f in dataclasses.fields(node):
        sub = f"{path}.{f.name}" if path else f.name
        other = f.metadata.get("at_most")
        if other is not None and getattr(node, f.name) > getattr(node, other):
            keys = (sub, f"{path}.{other}" if path else other)
            setters = [n for n, raw in sources if any(_has_key(raw, k) for k in keys)]
            raise ConfigError(
                f"{', '.join(setters) or 'the defaults'}: {keys[0]} = {getattr(node, f.name)} "
                f"is above {keys[1]} = {getattr(node, other)} (expected {f.name} <= {other})"
            )
        _check_pairs(getattr(node, f.name), sub, sources)


def _has_key(raw: Any, dotted: str) -> bool:
    for part in dotted.split("."):
        if not isinstance(raw, Mapping) or part not in raw:
            return False
        raw = raw[part]
    return True


def with_origin(cfg: Config, text: str | None) -> Config:
    """`cfg` with `--origin LAT,LON,ALT,HEADING` (degrees, degrees, metres, degrees) as
    geo.origin, validated like a config source; None: `cfg` unchanged."""
    if text is None:
        return cfg
    source = f"--origin {text}"
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4:
        raise ConfigError(
            f"{source}: expected LAT,LON,ALT,HEADING (4 numbers: latitude and longitude in "
            "degrees, ellipsoidal height in metres, heading of the nav x axis in degrees)"
        )
    raw = dict(zip(("lat_deg", "lon_deg", "alt_m", "heading_deg"), values, strict=True))
    geo = build_dataclass(GeoConfig, {"origin": raw}, "geo", source)
    return dataclasses.replace(cfg, geo=geo)


def dump_config(cfg: Config) -> str:
    """The resolved config as YAML text (what is written next to every output)."""
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)
