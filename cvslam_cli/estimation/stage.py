"""`cvslam fuse`: the filter over the run's features and the logs' motion data.

Inputs: `<run>/features/<vehicle>.npz` (extract, or the simulator's landmark mode) and the
logs they came from (recorded in the feature files and `run.yaml`; `*.mcap` beside
`features/` for a simulator output directory; or given explicitly) for the motion data (IMU,
odometry) and the initial pose (first ground-truth pose, `fuse.initial.source`).

Outputs, in `<run>/fuse/` (NH-infinity) or `<run>/fuse_ekf/` (`--filter ekf`), written to a
temporary folder renamed when complete (docs/fuse_outputs.md): per vehicle `<v>.tum`,
`<v>_deadreckoning.tum`, `<v>_pose_cov.npz`; `map.csv`, `map.ply`, `timeline.csv`,
`events.csv`, `result.mcap`.

With `fuse.prior_map` (`--prior-map`) the filter starts from an earlier run's map file
(`prior_map.py`); the map file's content is one of the inputs whose checksums decide
whether the stage is up to date.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import chi2
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from cvslam_cli import __version__
from cvslam_cli.config import Config, FuseConfig
from cvslam_cli.errors import CvslamError
from cvslam_cli.estimation.association import lookalike_bound
from cvslam_cli.estimation.filters import FilterSettings
from cvslam_cli.estimation.gauge import constrained
from cvslam_cli.estimation.landmark_coordinates import resolve
from cvslam_cli.estimation.lookalikes import pooled, sample_lookalikes
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import (
    ConstantVelocityModel,
    InitialUncertainty,
    InsModel,
    MotionModel,
    OdometryModel,
    odometry_input,
)
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.octave_noise import OctaveBearingNoise, match_octaves
from cvslam_cli.estimation.octave_noise import resolve as resolve_octaves
from cvslam_cli.estimation.rig_calibration import RightCxEstimates, estimate_right_cx
from cvslam_cli.estimation.settings import (
    RelocalisationSettings,
    SlamSettings,
    WindowSettings,
    landmark_bound,
)
from cvslam_cli.estimation.slam import (
    Slam,
    SlamResult,
    VehicleTrack,
    dead_reckoning_track,
    merge_results,
)
from cvslam_cli.estimation.update_budget import resolve as resolve_budget
from cvslam_cli.estimation.vehicle import VehicleInput
from cvslam_cli.features.pixel_noise import PixelNoise, pixel_noise, sample_pixel_noise
from cvslam_cli.geometry.camera import stereo_rig
from cvslam_cli.geometry.rotations import (
    euler_zyx_to_matrix,
    interpolate_positions,
    matrix_to_euler_zyx,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
    so3_log,
)
from cvslam_cli.io.atomic import atomic_dir, check_writable
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.fuse_files import (
    save_pose_covariances,
    write_csv_atomic,
    write_map_csv,
    write_map_ply,
)
from cvslam_cli.io.logs import LogSet, all_log_paths, open_logs, require_logs, with_run_bindings
from cvslam_cli.io.map_file import load_prior_map, save_map
from cvslam_cli.io.observations_file import save_observations
from cvslam_cli.io.result_mcap import write_result_mcap
from cvslam_cli.io.run_layout import FuseFolder, RunLayout, fuse_name
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.trajectory import write_tum
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.features import FeatureSet
from cvslam_cli.records.landmark_archive import LandmarkArchive
from cvslam_cli.records.log import ImuSample, OdometryRecord, PoseRecord
from cvslam_cli.records.poses import PoseTable

log = logging.getLogger("cvslam.fuse")

# fuse.association.pixel_sigma_px auto where the frames measure nothing (px): the pixel
# noise of the landmark-mode simulation, within 20 % of what KITTI's frames measure (0.42)
FALLBACK_PIXEL_SIGMA_PX = 0.5


@dataclass(frozen=True)
class VehicleFuse:
    frames: int
    model: str
    distance_m: float
    final_error_m: float  # nan without ground truth
    final_error_deadreckoning_m: float
    rmse_m: float
    rmse_deadreckoning_m: float
    final_sigma_m: float
    loop_closures: int
    # seconds from the vehicle's start until its pose was known: 0 for a known initial
    # pose, the localisation time for an unknown one, None if it was never localised
    localised_after_s: float | None = 0.0
    # the localisation's inlier landmarks (unknown initial pose; 0 otherwise)
    localised_inliers: int = 0
    # with a prior map: its landmarks this vehicle brought into the filter (at the
    # localisation and later), and seconds from its start to the first of them (None: none)
    prior_landmarks: int = 0
    first_prior_s: float | None = None
    # frames where it was lost (the map contradicted its pose, or it lost the map) and found
    # again in this run (estimation/relocalisation.py; events.csv's lost and relocalisation)
    lost: int = 0
    relocalised: int = 0


@dataclass(frozen=True)
class FuseSummary:
    out_dir: Path
    skipped: bool
    filter: str
    single: bool
    vehicles: dict[str, VehicleFuse]
    landmarks: int
    wall_s: float
    realtime_factor: float
    gamma_raised: int


# --------------------------------------------------------------------------- inputs


@dataclass(frozen=True, eq=False)
class _Motion:
    imu_stamps_ns: np.ndarray
    imu: np.ndarray  # (K, 6) accel, gyro
    odom_stamps_ns: np.ndarray
    odom: np.ndarray  # (K, 2)
    gt: PoseTable


def _sample_arrays(items: list[tuple[int, np.ndarray]], d: int) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (K,) int64, inputs (K, d)) of motion samples, in stamp order."""
    st = np.array([s for s, _ in items], dtype=np.int64)
    u = np.array([a for _, a in items], dtype=float).reshape(-1, d)
    order = np.argsort(st, kind="stable")
    return st[order], u[order]


def _read_motion(logs: LogSet, vehicles: list[str]) -> dict[str, _Motion]:
    imu: dict[str, list[tuple[int, np.ndarray]]] = {v: [] for v in vehicles}
    odo: dict[str, list[tuple[int, np.ndarray]]] = {v: [] for v in vehicles}
    gt: dict[str, list[PoseRecord]] = {v: [] for v in vehicles}
    present = [v for v in vehicles if v in logs.vehicles]
    for rec in logs.records(vehicles=present, roles=("imu", "odom", "ground_truth")):
        if isinstance(rec, ImuSample):
            imu[rec.vehicle].append((rec.stamp_ns, np.r_[rec.accel_m_s2, rec.gyro_rad_s]))
        elif isinstance(rec, OdometryRecord):
            odo[rec.vehicle].append((rec.stamp_ns, odometry_input(rec)))
        elif isinstance(rec, PoseRecord):
            gt[rec.vehicle].append(rec)
    out = {}
    for v in vehicles:
        i_st, i_u = _sample_arrays(imu[v], 6)
        o_st, o_u = _sample_arrays(odo[v], 2)
        g = gt[v]
        out[v] = _Motion(
            i_st,
            i_u,
            o_st,
            o_u,
            PoseTable(
                np.array([r.stamp_ns for r in g], dtype=np.int64),
                np.array([r.p_m for r in g], dtype=float).reshape(-1, 3),
                np.array([r.q_xyzw for r in g], dtype=float).reshape(-1, 4),
            ),
        )
    return out


def _auto_model(vehicle: str, motion: _Motion, fallback_cv: bool) -> tuple[str, str]:
    """The motion model the logs call for, and why: IMU -> ins, wheel odometry -> odometry,
    neither -> constant velocity (unless fuse.motion.fallback_constant_velocity is false)."""
    if len(motion.imu_stamps_ns):
        return "ins", "IMU in the logs"
    if len(motion.odom_stamps_ns):
        return "odometry", "wheel odometry in the logs, no IMU"
    if fallback_cv:
        return "constant_velocity", "no IMU or odometry in the logs"
    raise CvslamError(
        f"vehicle {vehicle}: no IMU or odometry messages in the logs and "
        "fuse.motion.fallback_constant_velocity is false; set it to true (or "
        "fuse.motion.model=constant_velocity) to track it with a constant-velocity model"
    )


def _model(cfg: FuseConfig, vehicle: str, motion: _Motion, z_nav_m: float) -> MotionModel:
    mc = cfg.motion
    kind = mc.model
    if kind == "auto":
        kind, why = _auto_model(vehicle, motion, mc.fallback_constant_velocity)
        log.info("%s: motion model %s (%s; fuse.motion.model to choose)", vehicle, kind, why)
    else:
        log.debug("%s: motion model %s (fuse.motion.model)", vehicle, kind)
    _log_motion_inputs(vehicle, kind, motion, mc)
    if kind == "ins":
        if not len(motion.imu_stamps_ns):
            raise CvslamError(f"vehicle {vehicle}: fuse.motion.model is ins but no IMU messages")
        return InsModel(
            InsNoise(
                mc.accel_noise_density,
                mc.gyro_noise_density,
                mc.accel_random_walk,
                mc.gyro_random_walk,
            ),
            biases=mc.imu_biases,
        )
    if kind == "odometry":
        if not len(motion.odom_stamps_ns):
            raise CvslamError(
                f"vehicle {vehicle}: fuse.motion.model is odometry but no odometry messages"
            )
        return OdometryModel(
            mc.odometry_speed_noise_density, mc.odometry_yaw_rate_noise_density, z_nav_m=z_nav_m
        )
    return ConstantVelocityModel(mc.cv_accel_noise_density, mc.cv_angular_accel_noise_density)


def _log_motion_inputs(vehicle: str, kind: str, motion: _Motion, mc: Any) -> None:
    """-v: the samples and the process noise the chosen motion model runs on."""
    if kind == "ins":
        log.debug(
            "%s: %d IMU samples; noise densities accel %.3g, gyro %.3g, random walks accel "
            "%.3g, gyro %.3g; biases %s (fuse.motion)",
            vehicle,
            len(motion.imu_stamps_ns),
            mc.accel_noise_density,
            mc.gyro_noise_density,
            mc.accel_random_walk,
            mc.gyro_random_walk,
            "estimated" if mc.imu_biases else "not estimated",
        )
    elif kind == "odometry":
        log.debug(
            "%s: %d odometry samples; noise densities speed %.3g, yaw rate %.3g (fuse.motion)",
            vehicle,
            len(motion.odom_stamps_ns),
            mc.odometry_speed_noise_density,
            mc.odometry_yaw_rate_noise_density,
        )
    else:
        log.debug(
            "%s: constant velocity; noise densities accel %.3g, angular accel %.3g (fuse.motion)",
            vehicle,
            mc.cv_accel_noise_density,
            mc.cv_angular_accel_noise_density,
        )


def _log_settings(
    cfg: FuseConfig, kind: str, settings: SlamSettings, inputs: list[VehicleInput]
) -> None:
    """-v: the filter, its bound, the association and map settings the run uses, and each
    vehicle's initial pose."""
    f = settings.filter
    if kind == "hinf":
        log.debug(
            "fuse: filter NH-infinity, gamma %g (fuse.hinf.gamma; where the bound does not "
            "exist gamma^2 is raised to %g x the largest eigenvalue, fuse.hinf.gamma_margin), "
            "bound on %s states (fuse.hinf.bound), c_w %g, c_v %g",
            f.gamma,
            f.gamma_margin,
            {"vehicle": "the vehicle", "observer": "the observing vehicle's"}.get(f.bound, "all"),
            f.c_w,
            f.c_v,
        )
    else:
        log.debug("fuse: filter EKF (no H-infinity bound: gamma, c_w, c_v unused)")
    log.debug(
        "fuse: association: pixel sigma %.2f px, gate chi2 %.2f, consistency chi2 %.2f (4 dof), "
        "descriptor ratio %.2f, max descriptor distance %.0f (fuse.association)",
        settings.pixel_sigma_px,
        settings.gate_chi2,
        settings.consistency_chi2,
        settings.descriptor_ratio,
        settings.max_descriptor_distance,
    )
    log.debug(
        "fuse: map: at most %d landmarks in the state with %d vehicle(s), %d new landmarks "
        "per frame, new ones ranked by %s (fuse.map)",
        landmark_bound(settings, len(inputs)),
        len(inputs),
        settings.max_new_per_frame,
        settings.new_landmark_priority,
    )
    w = settings.window
    if w.window:
        log.debug(
            "fuse: sliding window of %d pose clones per vehicle, at most %d feature tracks, "
            "track gate chi2 %.2f for the 5 rows of a two-frame track (fuse.window)",
            w.window,
            w.max_tracks,
            w.gate_chi2[5],
        )
    else:
        log.debug("fuse: no sliding window (fuse.window.clones 0): landmarks only")
    for v in inputs:
        at = [i for i, n in enumerate(v.model.state_names) if n in ("p_n", "p_e", "p_d")]
        log.debug(
            "%s: initial pose from %s at stamp %d ns, position (%s) m (fuse.initial)",
            v.name,
            initial_pose_source(cfg, v.name),
            v.start_ns,
            ", ".join(f"{x:.2f}" for x in np.asarray(v.x0)[at]),
        )


def _initial_pose(
    cfg: FuseConfig, vehicle: str, gt: PoseTable, first_frame_ns: int, first_motion_ns: int
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(start_ns, p (3,), euler (3,), v_nav (3,), w_body (3,)) from the first ground-truth
    pose at or after the first frame and motion sample (velocities by finite differences)."""
    t_min = max(first_frame_ns, first_motion_ns)
    if cfg.initial.source == "origin":
        return t_min, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    if len(gt) == 0:
        raise CvslamError(
            f"vehicle {vehicle}: no ground-truth pose in the logs for the initial pose; set "
            "fuse.initial.source=origin to start at the nav origin"
        )
    i = int(np.searchsorted(gt.stamps_ns, t_min))
    if i >= len(gt):
        raise CvslamError(f"vehicle {vehicle}: ground truth ends before the first frame")
    if i > 0 and t_min - gt.stamps_ns[i - 1] < gt.stamps_ns[i] - t_min:
        i -= 1  # the nearest sample (before the first frame is fine: the filter predicts)
    if not np.all(np.isfinite(gt.q_nav_body_xyzw[i])):
        raise CvslamError(
            f"vehicle {vehicle}: the ground truth has positions only (PointStamped), no "
            "initial attitude; give it with fuse.initial.poses.<vehicle> or set "
            "fuse.initial.source=origin"
        )
    R = quat_xyzw_to_matrix(gt.q_nav_body_xyzw[i])
    euler = matrix_to_euler_zyx(R)
    near = _nearest_three(len(gt), i)
    v_nav = _derivative_at(gt.stamps_ns[near], gt.p_nav_m[near], gt.stamps_ns[i])
    # the body's turn from pose i to each nearby pose (zero at i): its rate is w_body
    turns = np.array([so3_log(R.T @ quat_xyzw_to_matrix(q)) for q in gt.q_nav_body_xyzw[near]])
    w_body = _derivative_at(gt.stamps_ns[near], turns, gt.stamps_ns[i])
    return int(gt.stamps_ns[i]), gt.p_nav_m[i].copy(), euler, v_nav, w_body


def _nearest_three(n: int, i: int) -> slice:
    """The (at most) three of n samples nearest sample i: i and its neighbours, the first or
    last three at the ends."""
    lo = min(max(i - 1, 0), max(n - 3, 0))
    return slice(lo, min(lo + 3, n))


def _derivative_at(stamps_ns: I64, values: F64, at_ns: int) -> F64:
    """(d,) the rate of values (k, d) at `at_ns`: the derivative of the parabola through the
    k <= 3 samples (a line through two, zero with one). The initial velocity and turn rate
    from the ground truth: at its first sample a plain forward difference is the rate half a
    sample later (on a turn at 2.5 m/s^2 sampled at 10 Hz, 0.125 m/s off, more than the
    initial prior's 0.1 m/s allows); inside evenly sampled truth this is the central
    difference."""
    if len(values) < 2:
        return np.zeros(values.shape[1])
    t_s = (stamps_ns - at_ns) * 1e-9
    coeffs = np.polyfit(t_s, values, min(2, len(t_s) - 1))  # (degree + 1, d)
    return np.asarray(coeffs[-2], dtype=float)


def initial_pose_source(cfg: FuseConfig, vehicle: str) -> str:
    """Where a vehicle's initial pose came from, for the run's metadata."""
    init = cfg.initial
    source = "config" if vehicle in init.poses else init.source
    return f"unknown (rough prior from {source})" if vehicle in init.unknown else source


def build_inputs(
    cfg: Config, features: dict[str, FeatureSet], logs: LogSet
) -> tuple[list[VehicleInput], dict[str, PoseTable]]:
    vehicles = list(features)
    motion = _read_motion(logs, vehicles)
    init = cfg.fuse.initial
    unc = InitialUncertainty(
        init.position_sigma_m,
        init.attitude_sigma_rad,
        init.velocity_sigma_m_s,
        init.angular_rate_sigma_rad_s,
        init.accel_bias_sigma_m_s2,
        init.gyro_bias_sigma_rad_s,
    )
    for key, table in (("poses", init.poses), ("unknown", init.unknown)):
        missing = sorted(set(table) - set(vehicles))
        if missing:
            raise CvslamError(
                f"fuse.initial.{key}: no vehicle {', '.join(missing)} in this run "
                f"(vehicles: {', '.join(vehicles)})"
            )
    inputs = []
    for v in vehicles:
        fs = features[v]
        mo = motion[v]
        if fs.n_frames == 0:
            raise CvslamError(f"vehicle {v}: the feature file has no frames")
        gt = mo.gt
        given = init.poses.get(v)
        if given is not None:  # the ground robot's (constant) height, as its other states
            z0 = float(given.position_m[2])
        else:
            z0 = float(gt.p_nav_m[0, 2]) if len(gt) else 0.0
        model = _model(cfg.fuse, v, mo, z0)
        if model.kind == "ins":
            st, U = mo.imu_stamps_ns, mo.imu
        elif model.kind == "odometry":
            st, U = mo.odom_stamps_ns, mo.odom
        else:
            st, U = np.zeros(0, dtype=np.int64), np.zeros((0, 0))
        first_motion = int(st[0]) if len(st) else int(fs.frame_stamp_ns[0])
        if given is not None:
            start = max(int(fs.frame_stamp_ns[0]), first_motion)
            p0, e0 = np.array(given.position_m), np.array(given.euler_rad)
            v0, w0 = np.array(given.velocity_m_s), np.zeros(3)
        else:
            start, p0, e0, v0, w0 = _initial_pose(
                cfg.fuse, v, gt, int(fs.frame_stamp_ns[0]), first_motion
            )
        prior = init.unknown.get(v)
        if prior is not None:  # a rough prior only: moved, turned, and wide
            turn = euler_zyx_to_matrix(0.0, 0.0, prior.yaw_offset_rad)
            p0 = p0 + np.asarray(prior.offset_m)
            e0 = e0 + np.array([0.0, 0.0, prior.yaw_offset_rad])
            v0 = turn @ v0
        x0 = model.initial_state(p0, e0, v0, w0)
        P0 = model.initial_covariance(unc)
        if prior is not None:
            names = model.state_names
            for i, nm in enumerate(names):
                if nm in ("p_n", "p_e", "p_d"):
                    P0[i, i] = prior.position_sigma_m**2
                elif nm == "yaw":
                    P0[i, i] = prior.yaw_sigma_rad**2
        inputs.append(
            VehicleInput(
                v,
                model,
                x0,
                P0,
                start,
                st,
                U,
                fs,
                StereoObservationModel.from_rig(stereo_rig(fs.rig)),
                pose_known=prior is None,
            )
        )
    return inputs, {v: motion[v].gt for v in vehicles}


@dataclass(frozen=True)
class PixelSigma:
    """The filter's pixel noise per coordinate and where it came from: "configured"
    (fuse.association.pixel_sigma_px a number), "measured" (auto: `noise`, measured from
    the vehicles' frames) or "fallback" (auto, but the frames measured nothing)."""

    sigma_px: float
    source: str
    noise: PixelNoise | None = None


def pixel_sigma(cfg: FuseConfig, inputs: Sequence[VehicleInput]) -> PixelSigma:
    """fuse.association.pixel_sigma_px resolved: a number as it is; auto: the keypoints' noise
    measured from every vehicle's consecutive frames, pooled (`features/pixel_noise.py`), or
    FALLBACK_PIXEL_SIGMA_PX with a warning where no rig is rectified or the frames are too
    few."""
    configured = cfg.association.pixel_sigma_px
    if configured != "auto":
        return PixelSigma(float(configured), "configured")
    samples = [sample_pixel_noise(v.features, stereo_rig(v.features.rig)) for v in inputs]
    noise = pixel_noise(samples)
    if noise is None:
        log.warning(
            "fuse: fuse.association.pixel_sigma_px auto: the frames measured no pixel noise (%d "
            "re-found stereo points in %d consecutive frame pairs; a rig that is not rectified "
            "or too few frames); %.2f px assumed: set it to a number",
            sum(s.points for s in samples),
            sum(s.pairs for s in samples),
            FALLBACK_PIXEL_SIGMA_PX,
        )
        return PixelSigma(FALLBACK_PIXEL_SIGMA_PX, "fallback")
    log.info(
        "fuse: pixel noise %.2f px per coordinate, measured from %d stereo points re-found in "
        "%d consecutive frame pairs (their core: %.2f px; fuse.association.pixel_sigma_px auto)",
        noise.sigma_px,
        noise.points,
        noise.pairs,
        noise.core_sigma_px,
    )
    return PixelSigma(noise.sigma_px, "measured", noise)


# look-alikes per megapixel where the vehicles' frames show any (fuse.association.
# other_vehicle_lookalikes_per_mpx auto), and the share of matches with a look-alike in their
# own frame below which they show none (BENCHMARKS.md, "Fuse: another vehicle's landmark,
# inside a window that a look-alike would fill")
AUTO_LOOKALIKES_PER_MPX = 10.0
NO_LOOKALIKES_SHARE = 0.001


def lookalikes_per_mpx(
    cfg: FuseConfig, inputs: Sequence[VehicleInput], single: bool = False
) -> float:
    """fuse.association.other_vehicle_lookalikes_per_mpx resolved: a number as it is; auto:
    AUTO_LOOKALIKES_PER_MPX where the vehicles' own frames hold look-alikes (`lookalikes.py`:
    repeated textures), none where they hold none (synthetic descriptors) or where a vehicle
    has no other's landmarks to look for (alone in its filter, `single`, without a prior
    map)."""
    a = cfg.association
    if a.other_vehicle_lookalikes_per_mpx != "auto":
        return float(a.other_vehicle_lookalikes_per_mpx)
    if (single or len(inputs) < 2) and not cfg.prior_map:
        return 0.0
    sample = pooled(
        [
            sample_lookalikes(
                v.features, a.other_vehicle_descriptor_ratio, a.max_descriptor_distance
            )
            for v in inputs
        ]
    )
    found = sample.share >= NO_LOOKALIKES_SHARE
    log.info(
        "fuse: %.1f %% of %d stereo matches in %d frames have a look-alike in their own frame: "
        "%s (fuse.association.other_vehicle_lookalikes_per_mpx auto)",
        100 * sample.share,
        sample.matches,
        sample.frames,
        f"another vehicle's landmark is taken only where {AUTO_LOOKALIKES_PER_MPX:g} look-alikes "
        "per megapixel are less likely"
        if found
        else "no bound on the windows",
    )
    return AUTO_LOOKALIKES_PER_MPX if found else 0.0


def settings_for(cfg: FuseConfig, filter_kind: str, inputs: Sequence[VehicleInput]) -> SlamSettings:
    """`slam_settings` with the pixel noise (`pixel_sigma`) and the look-alikes
    (`lookalikes_per_mpx`) resolved for `inputs`."""
    return slam_settings(
        cfg, filter_kind, pixel_sigma(cfg, inputs).sigma_px, lookalikes_per_mpx(cfg, inputs)
    )


def slam_settings(
    cfg: FuseConfig, filter_kind: str, pixel_sigma_px: float, lookalikes_mpx: float = 0.0
) -> SlamSettings:
    """The filter's settings from the fuse config, with the pixel noise (`pixel_sigma`) and
    the look-alike density (`lookalikes_per_mpx`) resolved."""
    h = cfg.hinf
    a = cfg.association
    m = cfg.map
    return SlamSettings(
        filter=FilterSettings(filter_kind, h.gamma, h.c_w, h.c_v, h.bound, h.gamma_margin),
        pixel_sigma_px=pixel_sigma_px,
        gate_chi2=float(chi2.ppf(a.gate_probability, 4)),
        consistency_chi2=float(chi2.ppf(a.consistency_probability, 4)),
        descriptor_ratio=a.descriptor_ratio,
        other_vehicle_descriptor_ratio=a.other_vehicle_descriptor_ratio,
        other_vehicle_ratio_over_frame=a.other_vehicle_ratio_over_frame,
        other_vehicle_pixel_sigma_px=a.other_vehicle_pixel_sigma_px,
        other_vehicle_max_distance_ratio=a.other_vehicle_max_distance_ratio,
        other_vehicle_lookalike_bound=lookalike_bound(lookalikes_mpx),
        max_descriptor_distance=a.max_descriptor_distance,
        octave_bearing_variance=a.octave_bearing_variance,
        iterate_sigma_ratio=a.iterate_sigma_ratio,
        iterate_bearing_sigma_rad=a.iterate_bearing_sigma_rad,
        max_update_iterations=a.max_update_iterations,
        max_landmarks=m.max_landmarks,
        landmarks_per_added_vehicle=m.landmarks_per_added_vehicle,
        max_landmarks_total=m.max_landmarks_total,
        max_updates_per_frame=m.max_updates_per_frame,
        target_tracked=m.target_tracked,
        max_new_per_frame=m.max_new_per_frame,
        max_new_depth_sigma_ratio=m.max_new_depth_sigma_ratio,
        new_landmark_priority=m.new_landmark_priority,
        landmark_coordinates=m.landmark_coordinates,
        anchor_span_ns=int(m.anchor_span_s * 1e9),
        reanchor_max_landmarks=m.reanchor_max_landmarks,
        max_view_angle_rad=float(np.radians(m.max_view_angle_deg)),
        others_tracking_ns=int(m.others_tracking_s * 1e9),
        loop_closure_gap_ns=int(m.loop_closure_gap_s * 1e9),
        loop_closure_min_landmarks=m.loop_closure_min_landmarks,
        event_merge_ns=int(m.event_merge_s * 1e9),
        joint_initialisation=m.joint_initialisation,
        joint_init_window_ns=int(m.joint_init_window_s * 1e9),
        reactivation=m.reactivation,
        observability_constrained=cfg.observability_constrained,
        reactivation_inflation=m.reactivation_inflation,
        prior_map_inflation=m.prior_map_inflation,
        refined_prior_map_inflation=m.refined_prior_map_inflation,
        reactivation_min_absence_ns=int(m.reactivation_min_absence_s * 1e9),
        reactivation_min_landmarks=m.reactivation_min_landmarks,
        max_reactivated_per_frame=m.max_reactivated_per_frame,
        nis_window=cfg.divergence.window,
        nis_per_dof_max=cfg.divergence.nis_per_dof_max,
        localise_min_inliers=cfg.initial.localise_min_inliers,
        localise_reprojection_px=cfg.initial.localise_reprojection_px,
        localise_prior_chi2=float(chi2.ppf(cfg.initial.localise_prior_probability, 3)),
        localise_confirm_frames=cfg.initial.localise_confirm_frames,
        relocalisation=RelocalisationSettings(
            enabled=cfg.relocalisation.enabled,
            interval_ns=int(cfg.relocalisation.check_interval_s * 1e9),
            gate_chi2=float(chi2.ppf(cfg.relocalisation.gate_probability, 6)),
            position_sigma_m=cfg.relocalisation.position_sigma_m,
            velocity_sigma_m_s=cfg.relocalisation.velocity_sigma_m_s,
            attitude_sigma_rad=cfg.relocalisation.attitude_sigma_rad,
            max_per_vehicle=cfg.relocalisation.max_per_vehicle,
            uncertain_sigma_ratio=cfg.relocalisation.uncertain_sigma_ratio,
        ),
        window=WindowSettings(
            window=cfg.window.clones,
            max_tracks=cfg.window.max_tracks,
            # a track of L observations (L <= clones + 1) gives 4 L - 3 rows
            gate_chi2=tuple(
                float(chi2.ppf(cfg.window.gate_probability, max(d, 1)))
                for d in range(4 * cfg.window.clones + 2)
            ),
            match_gate_chi2=float(chi2.ppf(a.gate_probability, 4)),
            descriptor_ratio=a.descriptor_ratio,
            max_descriptor_distance=a.max_descriptor_distance,
        ),
    )


# --------------------------------------------------------------------------- outputs


def pose_table(track: VehicleTrack) -> PoseTable:
    q = np.array([matrix_to_quat_xyzw(euler_zyx_to_matrix(*e)) for e in track.euler_rad])
    return PoseTable(track.stamps_ns, track.p_nav_m, q.reshape(-1, 4))


def _errors(track: VehicleTrack, gt: PoseTable) -> tuple[float, float]:
    """(final error, RMSE) of positions against ground truth, NaN without truth."""
    if len(track.stamps_ns) == 0:
        return float("nan"), float("nan")
    err = np.linalg.norm(
        track.p_nav_m - interpolate_positions(gt.stamps_ns, gt.p_nav_m, track.stamps_ns), axis=1
    )
    ok = np.isfinite(err)
    if not ok.any():
        return float("nan"), float("nan")
    return float(err[ok][-1]), float(np.sqrt(np.mean(err[ok] ** 2)))


EVENT_COLUMNS = [
    "stamp_ns",
    "end_stamp_ns",
    "event",
    "vehicle",
    "other_vehicles",
    "frames",
    "landmarks",
    "max_absence_s",
    "detail",
]


def _write_outputs(
    out: FuseFolder,
    res: SlamResult,
    dr: dict[str, VehicleTrack],
    header: str,
    meta: dict[str, str],
    viewer: dict[str, Any],
) -> None:
    """Every fuse output; `viewer`: what result.mcap shows besides the estimates (the
    ground truth and the rigs, `write_result_mcap`'s keywords)."""
    tables = {v: pose_table(t) for v, t in res.tracks.items()}
    dr_tables = {v: pose_table(t) for v, t in dr.items()}
    for v, t in res.tracks.items():
        write_tum(out.trajectory(v), tables[v], header=f"{header}\nvehicle {v}: filter estimate")
        write_tum(
            out.trajectory(v, deadreckoning=True),
            dr_tables[v],
            header=f"{header}\nvehicle {v}: dead reckoning (same motion input, no correction)",
        )
        save_pose_covariances(out.pose_covariances(v), t.stamps_ns, t.pose_cov)
    table = res.landmarks
    write_map_csv(out.map_csv, table)
    write_map_ply(out.map_ply, table)
    save_map(out.map_npz, res.archive)
    write_csv_atomic(out.timeline, pd.DataFrame(res.timeline))
    write_csv_atomic(out.events, pd.DataFrame(res.events, columns=EVENT_COLUMNS))
    write_result_mcap(
        out.result_mcap,
        tables,
        table,
        pose_covariances={v: t.pose_cov for v, t in res.tracks.items()},
        deadreckoning=dr_tables,
        metadata=meta,
        **viewer,
    )
    _write_observations(out, res)


def _write_observations(out: FuseFolder, res: SlamResult) -> None:
    """The observations the filter used, for `cvslam refine` (docs/fuse_outputs.md)."""
    if res.observations is not None:
        save_observations(out.observations, res.observations)


def _header(kind: str) -> str:
    """The trajectory files' first line (no path: a run gives the same bytes wherever it is)."""
    return f"cvslam {__version__} fuse ({kind}), nav frame NED, body FRD"


def _metadata(kind: str, single: bool) -> dict[str, str]:
    """The run's description in result.mcap (no path, like `_header`)."""
    return {"filter": kind, "mode": _mode(single), "cvslam_version": __version__}


def _mode(single: bool) -> str:
    return "single" if single else "cooperative"


# --------------------------------------------------------------------------- stage steps


def _load_features(
    layout: RunLayout,
) -> tuple[list[Path], dict[str, FeatureSet], list[dict[str, Any]]]:
    """(the feature files, the feature set of each vehicle, the files' metadata)."""
    files = layout.feature_files(f"run `cvslam extract LOG... -o {layout.root}` first")
    loaded = [load_features(p) for p in files]
    return files, {fs.vehicle: fs for fs, _ in loaded}, [m for _, m in loaded]


def _outputs(out: FuseFolder, vehicles: Sequence[str]) -> list[Path]:
    """The files whose presence tells that the fuse run is complete (run.yaml)."""
    return [
        out.timeline, out.map_csv, out.map_npz, out.result_mcap,
        *(out.trajectory(v) for v in vehicles),
    ]  # fmt: skip


def _filter(
    inputs: list[VehicleInput],
    settings: SlamSettings,
    single: bool,
    desc: str,
    progress: bool,
    prior: LandmarkArchive | None = None,
    right_cx_sigma_px: float = 0.0,
) -> tuple[SlamResult, float, RightCxEstimates | None]:
    """(the filter's result over every frame, its wall time, the calibration pass's
    estimates): one filter for all vehicles, or one per vehicle (`single`) with the results
    merged; with right_cx_sigma_px > 0, after a calibration pass that estimates each rig's
    right principal point (`rig_calibration.py`; else None)."""
    n_frames = sum(int(np.sum(v.features.frame_stamp_ns >= v.start_ns)) for v in inputs)
    calibrating = right_cx_sigma_px > 0
    t0 = time.perf_counter()
    bar = tqdm(
        total=n_frames * (2 if calibrating else 1), desc=desc, unit="frame",
        disable=None if progress else True, leave=False,
    )  # fmt: skip
    estimates = None
    # one BLAS thread: the filter's matrices (hundreds of rows) are too small to gain from
    # threads, and OpenBLAS's thread hand-offs made every update ~3x slower on 2 cores
    with bar, threadpool_limits(limits=1, user_api="blas"):
        if calibrating:
            estimates = estimate_right_cx(
                inputs, settings, right_cx_sigma_px, single, prior, bar.update
            )
            _log_right_cx(estimates)
            inputs = estimates.corrected(inputs)
        if single:
            res = merge_results([Slam([v], settings, progress=bar.update).run() for v in inputs])
        else:
            res = Slam(inputs, settings, progress=bar.update, prior=prior).run()
    return res, time.perf_counter() - t0, estimates


def _check_rectified(inputs: list[VehicleInput]) -> None:
    """The calibration pass estimates a rectified rig's right principal point only."""
    for v in inputs:
        if not v.obs.rectified:
            raise CvslamError(
                f"fuse.calibration.estimate_right_cx: vehicle {v.name}'s stereo rig is not "
                "rectified (only a rectified rig's right principal point is estimated); set it "
                "to false for this run"
            )


def _log_right_cx(estimates: RightCxEstimates) -> None:
    """Say what the calibration pass found (`rig_calibration.py`)."""
    for name, (du, sd) in estimates.right_cx_px.items():
        log.info(
            "fuse %s: right camera's principal point u0 estimated %+.3f +- %.3f px by a "
            "calibration pass (fuse.calibration.estimate_right_cx); the run uses it",
            name, du, sd,
        )  # fmt: skip
    for name, why in estimates.not_estimated.items():
        log.warning(
            "fuse %s: right camera's principal point u0 %s; the rig is used as calibrated "
            "(fuse.calibration.estimate_right_cx)", name, why,
        )  # fmt: skip


def _refuse_diverged(
    res: SlamResult, inputs: list[VehicleInput], layout: RunLayout, name: str, kind: str
) -> None:
    """A diverged filter writes no outputs: only its timeline so far, and says where."""
    if res.divergence is None:
        return
    d = res.divergence
    t_rel = (d.stamp_ns - min(v.start_ns for v in inputs)) * 1e-9
    diag = layout.diverged_timeline(name)
    write_csv_atomic(diag, pd.DataFrame(res.timeline))
    raise CvslamError(
        f"{layout.root}: the {kind} filter diverged for {d.vehicle} at stamp {d.stamp_ns} ns "
        f"({t_rel:.2f} s into the run): {d.reason}; no outputs written (timeline so far: "
        f"{diag})"
    )


def _vehicle_fuse(
    v: VehicleInput, res: SlamResult, dr: VehicleTrack, truth: PoseTable
) -> VehicleFuse:
    """The summary of one vehicle's estimate: errors against the truth (and the dead
    reckoning's), distance, final sigma, loop closures, when it was localised."""
    tr = res.tracks[v.name]
    fe, rmse = _errors(tr, truth)
    fe_dr, rmse_dr = _errors(dr, truth)
    steps = np.diff(tr.p_nav_m, axis=0)
    loops = sum(1 for e in res.events if e["event"] == "loop_closure" and e["vehicle"] == v.name)
    localised_after_s: float | None = 0.0
    inliers = 0
    if not v.pose_known:
        found = [e for e in res.events if e["event"] == "localisation" and e["vehicle"] == v.name]
        localised_after_s = (found[0]["stamp_ns"] - v.start_ns) * 1e-9 if found else None
        inliers = int(found[0]["landmarks"]) if found else 0
    prior = [e for e in res.events if e["event"] == "prior_map" and e["vehicle"] == v.name]

    def frames(kind: str) -> int:  # events merge frames close in time: count the frames
        return sum(
            int(e["frames"]) for e in res.events if e["event"] == kind and e["vehicle"] == v.name
        )

    return VehicleFuse(
        frames=len(tr.stamps_ns),
        model=v.model.kind,
        distance_m=float(np.sum(np.linalg.norm(steps, axis=1))),
        final_error_m=fe,
        final_error_deadreckoning_m=fe_dr,
        rmse_m=rmse,
        rmse_deadreckoning_m=rmse_dr,
        final_sigma_m=float(np.sqrt(np.trace(tr.pose_cov[-1][:3, :3])))
        if len(tr.stamps_ns)
        else float("nan"),
        loop_closures=loops,
        localised_after_s=localised_after_s,
        localised_inliers=inliers,
        prior_landmarks=sum(int(e["landmarks"]) for e in prior),
        first_prior_s=(prior[0]["stamp_ns"] - v.start_ns) * 1e-9 if prior else None,
        lost=frames("lost"),
        relocalised=frames("relocalisation"),
    )


def _log_auto_choices(
    settings: SlamSettings, inputs: list[VehicleInput], single: bool, prior: bool
) -> dict[str, dict[str, Any]]:
    """Log what the landmark coordinates, the observability constraint, the bearing noise
    by octave and the landmarks a frame resolve to (auto: by the motion models of the
    vehicles in one filter, as `Slam` resolves them: every vehicle's own with --single) and
    return it per vehicle for run.yaml."""
    teams = [[v] for v in inputs] if single else [inputs]
    chosen: dict[str, dict[str, Any]] = {
        "landmark_coordinates": {},
        "observability_constrained": {},
        "octave_bearing_variance": {},
        "max_updates_per_frame": {},
        "target_tracked": {},
    }
    for team in teams:
        kinds = [v.model.kind for v in team]
        who = f"{team[0].name}: " if single else ""
        coords, why = resolve(settings.landmark_coordinates, kinds)
        log.info("fuse: %slandmarks in %s coordinates (%s)", who, coords, why)
        on, why = constrained(settings.observability_constrained, kinds, prior)
        log.info("fuse: %sobservability constraint %s (%s)", who, "on" if on else "off", why)
        factors, why = resolve_octaves(settings.octave_bearing_variance, kinds)
        octaves = [match_octaves(v.features) for v in team]
        if factors and OctaveBearingNoise.of(factors, octaves) is None:
            why += "; every keypoint gets x1 here"  # e.g. all of octave 0 (landmark mode)
        log.info(
            "fuse: %sbearing noise variance by SIFT octave %s (%s)",
            who,
            " / ".join(f"x{b:g}" for b in factors) if factors else "alike",
            why,
        )
        budget, why = resolve_budget(settings.max_updates_per_frame, settings.target_tracked, kinds)
        log.info(
            "fuse: %sat most %d landmarks updated a frame, new ones while fewer than %d (%s)",
            who,
            budget.max_updates,
            budget.target_tracked,
            why,
        )
        for v in team:
            chosen["landmark_coordinates"][v.name] = coords
            chosen["observability_constrained"][v.name] = on
            chosen["octave_bearing_variance"][v.name] = list(factors)
            chosen["max_updates_per_frame"][v.name] = budget.max_updates
            chosen["target_tracked"][v.name] = budget.target_tracked
    return chosen


def _record_summary(
    cfg: Config, summary: FuseSummary, inputs: list[VehicleInput]
) -> dict[str, Any]:
    """The fuse run's summary in run.yaml."""
    return {
        "filter": summary.filter,
        "mode": _mode(summary.single),
        "vehicles": {k: _plain(vars(x)) for k, x in summary.vehicles.items()},
        "landmarks": summary.landmarks,
        "realtime_factor": round(float(summary.realtime_factor), 2),
        "gamma_raised": summary.gamma_raised,
        "initial_pose": {v.name: initial_pose_source(cfg.fuse, v.name) for v in inputs},
    }


# --------------------------------------------------------------------------- stage


def run(
    cfg: Config,
    run_dir: Path,
    *,
    filter_kind: str | None = None,
    single: bool = False,
    log_paths: Sequence[Path] = (),
    force: bool = False,
    progress: bool = False,
) -> FuseSummary:
    kind = filter_kind or cfg.fuse.filter
    layout = RunLayout(run_dir)
    out = layout.fuse(fuse_name(kind, single))
    files, features, metas = _load_features(layout)
    cfg = dataclasses.replace(cfg, logs=with_run_bindings(cfg.logs, run_dir))
    logs_used = all_log_paths(list(log_paths) or layout.find_logs(metas), cfg.logs)
    require_logs(logs_used)  # a missing log named before the plan reads it
    prior_path, prior = _prior_map(cfg.fuse, out, single)
    rd = RunDir(run_dir)
    outputs = _outputs(out, list(features))
    inputs_used = [*files, *logs_used, *([prior_path] if prior_path else [])]
    plan = rd.plan(out.name, cfg, ("logs", "fuse"), inputs_used, outputs, force)
    if plan.action == "skip":
        log.info("fuse: %s is up to date (same config and inputs); --force to redo it", out.path)
        return FuseSummary(out.path, True, kind, single, {}, 0, 0.0, 0.0, 0)
    check_writable(outputs)  # before the work: a read-only folder, a name too long
    logs = open_logs(logs_used, cfg.logs)
    inputs, truth = build_inputs(cfg, features, logs)
    sigma = pixel_sigma(cfg.fuse, inputs)
    lookalikes = lookalikes_per_mpx(cfg.fuse, inputs, single)
    settings = slam_settings(cfg.fuse, kind, sigma.sigma_px, lookalikes)
    _log_settings(cfg.fuse, kind, settings, inputs)
    chosen = _log_auto_choices(settings, inputs, single, prior is not None)
    cal = cfg.fuse.calibration
    if cal.estimate_right_cx:
        _check_rectified(inputs)
    res, wall, estimates = _filter(
        inputs, settings, single, f"fuse ({kind})", progress, prior,
        cal.right_cx_sigma_px if cal.estimate_right_cx else 0.0,
    )  # fmt: skip
    dr = {v.name: dead_reckoning_track(v) for v in inputs}
    _refuse_diverged(res, inputs, layout, out.name, kind)
    span_s = max((v.features.frame_stamp_ns[-1] - v.start_ns) * 1e-9 for v in inputs)
    with atomic_dir(out.path) as tmp:
        viewer = {
            "ground_truth": truth,
            "rigs": {v: stereo_rig(fs.rig) for v, fs in features.items()},
        }
        _write_outputs(FuseFolder(tmp), res, dr, _header(kind), _metadata(kind, single), viewer)
    vehicles = {v.name: _vehicle_fuse(v, res, dr[v.name], truth[v.name]) for v in inputs}
    summary = FuseSummary(
        out.path,
        False,
        kind,
        single,
        vehicles,
        len(res.landmarks),
        wall,
        span_s / wall if wall > 0 else float("inf"),
        res.gamma_raised,
    )
    record = _record_summary(cfg, summary, inputs)
    record["pixel_sigma_px"] = {"value": round(sigma.sigma_px, 4), "source": sigma.source}
    if estimates is not None:  # the calibration pass's (rig_calibration.py)
        record["right_cx_px"] = {
            v: {"value": round(du, 4), "std": round(sd, 4)}
            for v, (du, sd) in estimates.right_cx_px.items()
        } | {v: {"not_estimated": why} for v, why in estimates.not_estimated.items()}
    record.update(chosen)
    if prior is not None and prior_path is not None:
        record["prior_map"] = _prior_summary(prior_path, prior, res, run_dir)
    rd.record(out.name, plan, outputs, record, wall)
    return summary


def _prior_map(
    cfg: FuseConfig, out: FuseFolder, single: bool
) -> tuple[Path | None, LandmarkArchive | None]:
    """(the map file, its archive) of `fuse.prior_map`, or (None, None) without one."""
    if not cfg.prior_map:
        return None, None
    path, prior = load_prior_map(cfg.prior_map)
    if single:
        raise CvslamError(
            f"fuse.prior_map: {path}: --single does not start from a prior map (each vehicle's "
            "filter would bring its own copy of it); fuse without --single"
        )
    if path.resolve().parent == out.path.resolve():
        raise CvslamError(
            f"fuse.prior_map: {path} is this run's own output, which the run replaces; copy it "
            "elsewhere first"
        )
    log.info(
        "fuse: starting from the prior map %s: %d landmarks of %s (sessions up to %d)",
        path,
        len(prior),
        ", ".join(prior.vehicles),
        int(prior.session.max()) if len(prior) else 0,
    )
    return path, prior


def _prior_summary(
    path: Path, prior: LandmarkArchive, res: SlamResult, run_dir: Path
) -> dict[str, Any]:
    """run.yaml's record of the prior map: the file, its landmarks, how many this run used
    again and how many it added (docs/fuse_outputs.md, "Multi-session")."""
    a = res.archive
    n = len(prior)
    used = int(np.sum(a.n_observations[:n] > prior.n_observations)) if n else 0
    session = int(prior.session.max()) + 1 if n else 1
    try:
        shown = str(path.resolve().relative_to(run_dir.resolve()))
    except ValueError:
        shown = str(path)
    log.info(
        "fuse: prior map: %d of its %d landmarks observed again, %d new landmarks (session %d)",
        used,
        n,
        len(a) - n,
        session,
    )
    return {
        "file": shown,
        "landmarks": n,
        "observed_again": used,
        "new_landmarks": len(a) - n,
        "session": session,
        **_offset(res),
    }


def _offset(res: SlamResult) -> dict[str, Any]:
    """The prior map's common offset the run estimated (`prior_map.py`), for run.yaml."""
    if res.prior_offset_m is None or res.prior_offset_cov_m2 is None:
        return {}
    sigma = np.sqrt(np.maximum(np.diag(res.prior_offset_cov_m2), 0.0))
    log.info(
        "fuse: prior map offset (%s) m, sigma (%s) m",
        ", ".join(f"{x:.3f}" for x in res.prior_offset_m),
        ", ".join(f"{x:.3f}" for x in sigma),
    )
    return {
        "offset_m": [round(float(x), 4) for x in res.prior_offset_m],
        "offset_sigma_m": [round(float(x), 4) for x in sigma],
    }


def _plain(d: dict[str, Any]) -> dict[str, Any]:
    return {
        k: (round(float(v), 6) if isinstance(v, (float, np.floating)) else v) for k, v in d.items()
    }
