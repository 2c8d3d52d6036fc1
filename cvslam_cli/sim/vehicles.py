"""From a scenario's vehicle section to what the simulator runs: the stereo rig (cameras with
their mounting and calibration) and the trajectory over the vehicle's recording interval."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cvslam_cli.errors import ConfigError
from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, invert_T, make_T
from cvslam_cli.records.arrays import F64
from cvslam_cli.sim.scenario import SimVehicle, StereoRigSpec
from cvslam_cli.sim.trajectory import MotionSample, Trajectory, waypoint_trajectory

# camera optical axes (x right, y down, z forward) in the body frame (x fwd, y right, z down)
R_BODY_CAM_DOWN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
R_BODY_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def build_rig(name: str, spec: StereoRigSpec) -> StereoRig:
    """The stereo rig of `spec`; frame ids follow cvslam's naming."""
    R_mount = R_BODY_CAM_DOWN if spec.mount == "down" else R_BODY_CAM_FORWARD
    tilt = np.deg2rad(spec.tilt_deg)
    # rotation about the camera x axis turning the optical axis towards the image's +y
    R_tilt = np.array(
        [[1.0, 0, 0], [0, np.cos(tilt), np.sin(tilt)], [0, -np.sin(tilt), np.cos(tilt)]]
    )
    T_body_left = make_T(R_mount @ R_tilt, np.asarray(spec.lever_arm_m))
    if spec.rectified:
        R_left_right = np.eye(3)
        D = np.zeros(5)
        model = "plumb_bob"
    else:
        roll, pitch, yaw = np.deg2rad(spec.right_rotation_deg)
        R_left_right = euler_zyx_to_matrix(roll, pitch, yaw)
        D = np.zeros(5)
        D[: len(spec.distortion)] = spec.distortion[:5]
        model = "plumb_bob"
    T_left_right = make_T(R_left_right, np.array([spec.baseline_m, 0.0, 0.0]))
    K = np.array([[spec.fx, 0.0, spec.cx], [0.0, spec.fy, spec.cy], [0.0, 0.0, 1.0]])
    left = CameraModel(
        width=spec.width,
        height=spec.height,
        K=K,
        D=D.copy(),
        distortion_model=model,
        P=np.hstack([K, np.zeros((3, 1))]),
        T_body_cam=T_body_left,
        frame_id=f"{name}/left_camera_optical",
        source="simulator",
    )
    # exact projection of LEFT-camera points into the right image (rectified: [K | -f b])
    T_right_left = invert_T(T_left_right)
    right = CameraModel(
        width=spec.width,
        height=spec.height,
        K=K,
        D=D.copy(),
        distortion_model=model,
        P=K @ T_right_left[:3, :],
        T_body_cam=T_body_left @ T_left_right,
        frame_id=f"{name}/right_camera_optical",
        source="simulator",
    )
    rig = StereoRig(left, right)
    rig.validate(f"vehicle {name}")
    return rig


@dataclass(frozen=True, eq=False)
class VehiclePath:
    """A vehicle's trajectory over [t_start_s, t_end_s] of scenario time; a closed path
    repeats with its period (lap after lap)."""

    trajectory: Trajectory
    closed: bool
    t_start_s: float
    t_end_s: float

    @property
    def period_s(self) -> float:
        return self.trajectory.t1_s - self.trajectory.t0_s

    def sample(self, t_s: F64) -> MotionSample:
        t = np.asarray(t_s, dtype=float)
        tau = t - self.t_start_s
        if self.closed:
            tau = np.mod(tau, self.period_s)
        sample = self.trajectory.sample(self.trajectory.t0_s + tau)
        return replace(sample, t_s=t)


def build_path(name: str, v: SimVehicle, duration_s: float, source: str) -> VehiclePath:
    key = f"{source}: vehicles.{name}.waypoints_nav_m"
    wps = np.asarray(v.waypoints_nav_m, dtype=float)
    if v.kind == "ugv":
        wps = wps.copy()
        wps[:, 2] = 0.0
    try:
        traj = waypoint_trajectory(wps, v.speed_m_s, kind=v.kind, closed=v.closed)
    except ValueError as exc:
        raise ConfigError(f"{key}: {exc}") from None
    path = VehiclePath(traj, v.closed, v.start_s, duration_s)
    needed = duration_s - v.start_s
    if not v.closed and needed > path.period_s + 1e-9:
        raise ConfigError(
            f"{key}: the open path takes {path.period_s:.1f} s at "
            f"{v.speed_m_s:g} m/s but the vehicle records for {needed:.1f} s "
            "(close the loop, add waypoints or shorten the scenario)"
        )
    return path


def sample_times(t_start_s: float, t_end_s: float, rate_hz: float) -> F64:
    """Sample times start, start + 1/rate, ... up to and including end (seconds)."""
    n = int(np.floor((t_end_s - t_start_s) * rate_hz + 1e-9)) + 1
    return t_start_s + np.arange(n) / rate_hz


def camera_poses(path: VehiclePath, rig: StereoRig, t_s: F64) -> tuple[F64, F64, MotionSample]:
    """(N, 4, 4) T_nav_left, (N, 4, 4) T_nav_right and the motion sample at `t_s`."""
    m = path.sample(t_s)
    T_nav_body = np.tile(np.eye(4), (len(t_s), 1, 1))
    T_nav_body[:, :3, :3] = m.C_nav_body
    T_nav_body[:, :3, 3] = m.p_nav_m
    return T_nav_body @ rig.left.T_body_cam, T_nav_body @ rig.right.T_body_cam, m
