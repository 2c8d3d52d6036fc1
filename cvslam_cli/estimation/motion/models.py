"""Motion models of the filter behind one interface: the vehicle block of the state (eq. 3),
its process model (eq. 1, 2) and its process noise.

Three models, all frozen dataclasses holding their parameters:

- `InsModel` (UAV with an IMU): the paper's 6-DOF INS mechanisation (eq. 1, 2; see
  `cvslam_cli.estimation.motion`), 9 states p (nav, m), v (body, m/s), Psi (roll, pitch, yaw,
  rad), or 15 with accelerometer and gyro biases. Input u = [f^b (3) m/s^2, w^b (3) rad/s].
- `OdometryModel` (ground robot with wheel odometry): the paper's 3-DOF subset (x north,
  y east, yaw), input u = [forward speed m/s, yaw rate rad/s (FRD: positive turns from north
  towards east)]; `odometry_input` makes u from a nav_msgs/Odometry record.
- `ConstantVelocityModel` (no motion sensor, e.g. KITTI): 12 states p (nav), v (nav),
  Psi, w (body rates), driven by white acceleration and angular acceleration; no input.

A step returns (x+, F = dx+/dx, Q), Q the process noise of that step already mapped into the
state space (the paper's Gamma Q Gamma^T), so a filter predicts P <- F P F^T + Q. Between two
camera frames `propagate` composes the K motion steps into one (F_total, Q_total): the
landmarks are static (eq. 1: m_k = m_{k-1}), so their cross-covariances need only one
product per frame, P_vm <- F_total P_vm, and P_vv <- F_total P_vv F_total^T + Q_total.

Euler angles are not wrapped by the models (the state is continuous); compare them modulo 2 pi.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from cvslam_cli.estimation.motion.ins import InsNoise, euler_rate_matrix, ins_step_terms
from cvslam_cli.geometry.gravity import G_M_S2
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.log import OdometryRecord


@dataclass(frozen=True)
class InitialUncertainty:
    """Standard deviations of the initial vehicle state, per axis.

    position_m: m; attitude_rad: rad (each Euler angle); velocity_m_s: m/s (each axis);
    angular_rate_rad_s: rad/s (constant-velocity model's body rates); accel_bias_m_s2: m/s^2;
    gyro_bias_rad_s: rad/s (INS model with bias states). A model uses those it has states for.
    """

    position_m: float
    attitude_rad: float
    velocity_m_s: float
    angular_rate_rad_s: float
    accel_bias_m_s2: float
    gyro_bias_rad_s: float

    def __post_init__(self) -> None:
        _check_nonnegative("initial uncertainty", self, tuple(self.__dataclass_fields__))


@runtime_checkable
class MotionModel(Protocol):
    """The vehicle block of the filter state and its process model (read-only attributes:
    kind "ins" | "odometry" | "constant_velocity"; n, the size of the block; input_size,
    numbers per motion input sample (ins 6, odometry 2, constant_velocity 0); state_names,
    n names)."""

    @property
    def kind(self) -> str: ...

    @property
    def n(self) -> int: ...

    @property
    def input_size(self) -> int: ...

    @property
    def state_names(self) -> tuple[str, ...]: ...

    def step(self, x: F64, u: F64, dt: float) -> tuple[F64, F64, F64]:
        """One step: (x_new (n,), F (n, n) = dx_new/dx, Q (n, n) process noise of this step
        in state space). u (input_size,), dt seconds (>= 0)."""
        ...

    def pose(self, x: F64) -> tuple[F64, F64]:
        """(p_nav_m (3,), euler_rad (3,) roll, pitch, yaw) of the body."""
        ...

    def pose_jacobian(self, x: F64) -> F64:
        """(6, n): d (p, Psi) / d x."""
        ...

    def initial_state(self, p_nav_m: F64, euler_rad: F64, v_nav_m_s: F64, w_body_rad_s: F64) -> F64:
        """(n,) state of a body at p_nav_m (3,) m with attitude euler_rad (3,), velocity
        v_nav_m_s (3,) in the nav frame and body rates w_body_rad_s (3,); a model keeps what
        it has states for (biases start at zero)."""
        ...

    def initial_covariance(self, init: InitialUncertainty) -> F64:
        """(n, n) diagonal covariance from the standard deviations of `init`."""
        ...

    def with_pose(self, x: F64, p_nav_m: F64, euler_rad: F64) -> F64:
        """(n,) state x moved to the pose (p_nav_m, euler_rad), the motion it carries kept
        (a velocity in the nav frame turns with the attitude; body-frame states and biases
        stay). Used to relinearise a vehicle that was localised in the map."""
        ...


def _check_nonnegative(what: str, obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{what} {name}: expected a finite number >= 0, got {value!r}")


def _vec3(a: F64, name: str) -> F64:
    v = np.asarray(a, dtype=float).reshape(-1)
    if v.shape != (3,):
        raise ValueError(f"{name}: expected 3 numbers, got shape {np.shape(a)}")
    return v


# ----------------------------------------------------------------------------- INS


def inertial_team(motion_kinds: Sequence[str]) -> bool:
    """Whether a vehicle of a team whose vehicles have these motion models
    (`MotionModel.kind`) has an IMU: what three `auto` settings of a team go by (the
    landmark coordinates, the bearing noise by octave and the update budget; the
    observability constraint goes by `gauge.motion_measured`). A team with an aerial vehicle
    maps the way its aerial vehicles need (far ground, a gauge of translation and heading),
    ground vehicles in it included: on the mixed team (`mixed_yard`, UAVs and ground robots)
    every kind of vehicle was more accurate so than with the settings of a ground team
    (BENCHMARKS.md, "Fuse: a mixed team mapped the aerial way"); a team of ground vehicles
    alone keeps those."""
    return any(k == "ins" for k in motion_kinds)


@dataclass(frozen=True)
class InsModel:
    """6-DOF INS mechanisation (eq. 1, 2) on IMU samples, u = [f^b (3) m/s^2, w^b (3) rad/s]
    (specific force and angular rate, body FRD). 15 states with `biases` (p, v^b, Psi, b_a,
    b_g), else 9. Q = G diag(q) G^T with white-noise variance density^2 / dt per sample and
    bias-walk variance density^2 dt (`ins_process_noise`); g_nav (3,) m/s^2, NED gravity."""

    noise: InsNoise
    biases: bool = True
    g_nav: tuple[float, float, float] = (0.0, 0.0, G_M_S2)
    kind: Literal["ins"] = field(default="ins", init=False)
    input_size: int = field(default=6, init=False)

    def __post_init__(self) -> None:
        g = tuple(float(c) for c in _vec3(np.asarray(self.g_nav), "g_nav"))
        object.__setattr__(self, "g_nav", g)
        _check_nonnegative("INS noise", self.noise, tuple(InsNoise.__dataclass_fields__))

    @property
    def n(self) -> int:
        return 15 if self.biases else 9

    @property
    def state_names(self) -> tuple[str, ...]:
        names = ("p_n", "p_e", "p_d", "v_x", "v_y", "v_z", "roll", "pitch", "yaw")
        if self.biases:
            names += ("b_ax", "b_ay", "b_az", "b_gx", "b_gy", "b_gz")
        return names

    @cached_property
    def _sigma_rate(self) -> F64:
        """(n_noise,) noise standard deviations per sqrt(s): Q = Gu diag(_sigma_rate^2 dt) Gu^T
        with the unit-scaled Gu of `ins_step_terms` (sensor noise: (density^2 / dt) dt^2 =
        density^2 dt; bias walk: density^2 dt)."""
        z = self.noise
        s = [z.accel_noise_density] * 3 + [z.gyro_noise_density] * 3
        if self.biases:
            s += [z.accel_random_walk] * 3 + [z.gyro_random_walk] * 3
        return np.array(s)

    @cached_property
    def _g(self) -> F64:
        return np.array(self.g_nav)

    def step(self, x: F64, u: F64, dt: float) -> tuple[F64, F64, F64]:
        """Eq. 1, 2 for one IMU interval dt s with u (6,) held over it: (x+, F, Q)."""
        x_new, F, Gu = ins_step_terms(x, u[0:3], u[3:6], dt, self._g)
        M = Gu * (self._sigma_rate * math.sqrt(dt))
        return x_new, F, M @ M.T  # M M^T: exactly symmetric

    def pose(self, x: F64) -> tuple[F64, F64]:
        return np.array(x[0:3], dtype=float), np.array(x[6:9], dtype=float)

    def pose_jacobian(self, x: F64) -> F64:
        J = np.zeros((6, self.n))
        J[0:3, 0:3] = np.eye(3)
        J[3:6, 6:9] = np.eye(3)
        return J

    def initial_state(self, p_nav_m: F64, euler_rad: F64, v_nav_m_s: F64, w_body_rad_s: F64) -> F64:
        """[p, v^b = C_nav_body^T v^n, Psi (, zero biases)]; w_body_rad_s is not a state."""
        psi = _vec3(euler_rad, "euler_rad")
        v_body = euler_zyx_to_matrix(*psi).T @ _vec3(v_nav_m_s, "v_nav_m_s")
        x = np.zeros(self.n)
        x[0:3] = _vec3(p_nav_m, "p_nav_m")
        x[3:6] = v_body
        x[6:9] = psi
        return x

    def initial_covariance(self, init: InitialUncertainty) -> F64:
        s = [init.position_m] * 3 + [init.velocity_m_s] * 3 + [init.attitude_rad] * 3
        if self.biases:
            s += [init.accel_bias_m_s2] * 3 + [init.gyro_bias_rad_s] * 3
        return np.diag(np.square(s))

    def with_pose(self, x: F64, p_nav_m: F64, euler_rad: F64) -> F64:
        """p and Psi replaced; v (body frame) and the biases kept."""
        x_new = np.array(x, dtype=float)
        x_new[0:3] = _vec3(p_nav_m, "p_nav_m")
        x_new[6:9] = _vec3(euler_rad, "euler_rad")
        return x_new


# ----------------------------------------------------------------------------- odometry


def odometry_input(rec: OdometryRecord, twist_frame: Literal["frd", "flu"] = "frd") -> F64:
    """u (2,) = [forward speed m/s, yaw rate rad/s (positive from north towards east)] of an
    `OdometryRecord` (nav_msgs/Odometry; its twist is in `child_frame_id`, the body).

    cvslam logs carry the body frame FRD (DESIGN.md section 3; the simulator writes
    `linear = [v, 0, 0]`, `angular = [0, 0, w_z]` with w_z the FRD body yaw rate, which is
    the NED yaw rate of a level robot, see `cvslam_cli/sim/stage.py` and
    `cvslam_cli/sim/odometry.py`), so the default is u = [linear.x, angular.z] unchanged.
    A log recorded on a ROS robot (REP 103, base_link FLU, angular.z > 0 turning
    counter-clockwise seen from above) needs twist_frame="flu": forward is still x, and the
    yaw rate about the downward axis is -angular.z.
    """
    lin = np.asarray(rec.linear_m_s, dtype=float).reshape(-1)
    ang = np.asarray(rec.angular_rad_s, dtype=float).reshape(-1)
    if lin.shape != (3,) or ang.shape != (3,):
        raise ValueError(
            f"odometry twist of {rec.vehicle} at {rec.stamp_ns} ns: expected 3 + 3 numbers, "
            f"got {lin.shape} and {ang.shape}"
        )
    if twist_frame == "frd":
        return np.array([lin[0], ang[2]])
    if twist_frame == "flu":
        return np.array([lin[0], -ang[2]])
    raise ValueError(f"twist_frame: expected 'frd' or 'flu', got {twist_frame!r}")


def _sinc_terms(a: float) -> tuple[float, float]:
    """sin(a)/a and its derivative, accurate near 0."""
    if abs(a) < 1e-4:
        a2 = a * a
        return 1.0 - a2 / 6.0 + a2 * a2 / 120.0, a * (-1.0 / 3.0 + a2 / 30.0)
    s, c = math.sin(a), math.cos(a)
    return s / a, (a * c - s) / (a * a)


@dataclass(frozen=True)
class OdometryModel:
    """3-DOF ground robot (x north, y east, yaw; the paper's subset of eq. 1 for ground
    robots) on wheel odometry u = [v forward m/s, w yaw rate rad/s] (`odometry_input`).

    The step is the exact motion on a circular arc for u held over dt (unicycle):
        x+ = x + s cos(yaw + w dt / 2),   y+ = y + s sin(yaw + w dt / 2),   yaw+ = yaw + w dt
    with chord s = v dt sinc(w dt / 2); for w -> 0 it is eq. 1's Euler step.
    Noise: white speed and yaw-rate noise, densities speed_noise_density m/s/sqrt(Hz) and
    yaw_rate_noise_density rad/s/sqrt(Hz), variance per step density^2 / dt. The robot drives
    at the fixed height z_nav_m (nav, down, m) with zero roll and pitch.
    """

    speed_noise_density: float
    yaw_rate_noise_density: float
    z_nav_m: float = 0.0
    kind: Literal["odometry"] = field(default="odometry", init=False)
    n: int = field(default=3, init=False)
    input_size: int = field(default=2, init=False)
    state_names: tuple[str, ...] = field(default=("p_n", "p_e", "yaw"), init=False)

    def __post_init__(self) -> None:
        _check_nonnegative("odometry", self, ("speed_noise_density", "yaw_rate_noise_density"))
        if not math.isfinite(self.z_nav_m):
            raise ValueError(f"z_nav_m: expected a finite number, got {self.z_nav_m}")

    def step(self, x: F64, u: F64, dt: float) -> tuple[F64, F64, F64]:
        """One odometry interval dt s with u (2,) held over it: (x+ (3,), F (3, 3), Q (3, 3))."""
        px, py, yaw = x.tolist()
        v, w = float(u[0]), float(u[1])
        half = 0.5 * w * dt
        sinc, dsinc = _sinc_terms(half)
        s = v * dt * sinc
        h = yaw + half
        ch, sh = math.cos(h), math.sin(h)
        x_new = np.array([px + s * ch, py + s * sh, yaw + w * dt])
        F = np.array([[1.0, 0.0, -s * sh], [0.0, 1.0, s * ch], [0.0, 0.0, 1.0]])
        # unit-scaled noise Jacobian Gu = dx+/du / dt (finite as dt -> 0)
        k = 0.5 * v * dt
        Gu = np.array(
            [
                [sinc * ch, k * (dsinc * ch - sinc * sh)],
                [sinc * sh, k * (dsinc * sh + sinc * ch)],
                [0.0, 1.0],
            ]
        )
        M = Gu * (np.array([self.speed_noise_density, self.yaw_rate_noise_density]) * math.sqrt(dt))
        return x_new, F, M @ M.T  # variance per step density^2 / dt on u = Gu dt

    def pose(self, x: F64) -> tuple[F64, F64]:
        return np.array([x[0], x[1], self.z_nav_m], dtype=float), np.array(
            [0.0, 0.0, x[2]], dtype=float
        )

    def pose_jacobian(self, x: F64) -> F64:
        J = np.zeros((6, 3))
        J[0, 0] = J[1, 1] = J[5, 2] = 1.0
        return J

    def initial_state(self, p_nav_m: F64, euler_rad: F64, v_nav_m_s: F64, w_body_rad_s: F64) -> F64:
        """[p_n, p_e, yaw]; height, roll, pitch, velocity and rates are not states."""
        p = _vec3(p_nav_m, "p_nav_m")
        return np.array([p[0], p[1], _vec3(euler_rad, "euler_rad")[2]])

    def initial_covariance(self, init: InitialUncertainty) -> F64:
        return np.diag(np.square([init.position_m, init.position_m, init.attitude_rad]))

    def with_pose(self, x: F64, p_nav_m: F64, euler_rad: F64) -> F64:
        return self.initial_state(p_nav_m, euler_rad, np.zeros(3), np.zeros(3))


# ----------------------------------------------------------------------------- constant velocity


@dataclass(frozen=True)
class ConstantVelocityModel:
    """No motion sensor: 12 states p (nav, m), v (nav, m/s), Psi (rad), w (body, rad/s);
    no input (u of size 0).

        p+ = p + v dt,   v+ = v,   Psi+ = Psi + E(Psi) w dt,   w+ = w

    driven by white acceleration (accel_noise_density, m/s^2/sqrt(Hz), per nav axis) and
    white angular acceleration (angular_accel_noise_density, rad/s^2/sqrt(Hz), per body axis):
    the discretised white-noise-acceleration blocks q [[dt^3/3, dt^2/2], [dt^2/2, dt]] for
    (p, v) and, through E (linearised), for (Psi, w).
    """

    accel_noise_density: float
    angular_accel_noise_density: float
    kind: Literal["constant_velocity"] = field(default="constant_velocity", init=False)
    n: int = field(default=12, init=False)
    input_size: int = field(default=0, init=False)
    state_names: tuple[str, ...] = field(
        default=(
            "p_n", "p_e", "p_d", "v_n", "v_e", "v_d",
            "roll", "pitch", "yaw", "w_x", "w_y", "w_z",
        ),
        init=False,
    )  # fmt: skip

    def __post_init__(self) -> None:
        _check_nonnegative(
            "constant velocity", self, ("accel_noise_density", "angular_accel_noise_density")
        )

    def step(self, x: F64, u: F64, dt: float) -> tuple[F64, F64, F64]:
        """One interval of dt s (u ignored, size 0): (x+ (12,), F (12, 12), Q (12, 12))."""
        psi, w = x[6:9], x[9:12]
        E, dE = euler_rate_matrix(psi)
        x_new = np.array(x, dtype=float)
        x_new[0:3] += x[3:6] * dt
        x_new[6:9] += E @ w * dt
        F = np.eye(12)
        F[0:3, 3:6] = np.eye(3) * dt
        F[6:9, 6:8] += (dE @ w).T * dt  # d(E w)/d(roll, pitch)
        F[6:9, 9:12] = E * dt
        qa, qw = self.accel_noise_density**2, self.angular_accel_noise_density**2
        a, b, c = dt**3 / 3.0, dt**2 / 2.0, dt
        Q = np.zeros((12, 12))
        Q[0:3, 0:3] = np.eye(3) * (qa * a)
        Q[0:3, 3:6] = Q[3:6, 0:3] = np.eye(3) * (qa * b)
        Q[3:6, 3:6] = np.eye(3) * (qa * c)
        Q[6:9, 6:9] = (E @ E.T) * (qw * a)
        Q[6:9, 9:12] = E * (qw * b)
        Q[9:12, 6:9] = E.T * (qw * b)
        Q[9:12, 9:12] = np.eye(3) * (qw * c)
        return x_new, F, Q

    def pose(self, x: F64) -> tuple[F64, F64]:
        return np.array(x[0:3], dtype=float), np.array(x[6:9], dtype=float)

    def pose_jacobian(self, x: F64) -> F64:
        J = np.zeros((6, 12))
        J[0:3, 0:3] = np.eye(3)
        J[3:6, 6:9] = np.eye(3)
        return J

    def initial_state(self, p_nav_m: F64, euler_rad: F64, v_nav_m_s: F64, w_body_rad_s: F64) -> F64:
        return np.concatenate(
            [
                _vec3(p_nav_m, "p_nav_m"),
                _vec3(v_nav_m_s, "v_nav_m_s"),
                _vec3(euler_rad, "euler_rad"),
                _vec3(w_body_rad_s, "w_body_rad_s"),
            ]
        )

    def initial_covariance(self, init: InitialUncertainty) -> F64:
        s = (
            [init.position_m] * 3
            + [init.velocity_m_s] * 3
            + [init.attitude_rad] * 3
            + [init.angular_rate_rad_s] * 3
        )
        return np.diag(np.square(s))

    def with_pose(self, x: F64, p_nav_m: F64, euler_rad: F64) -> F64:
        """p and Psi replaced; v (nav frame) turned with the attitude, w (body) kept."""
        psi = _vec3(euler_rad, "euler_rad")
        turn = euler_zyx_to_matrix(*psi) @ euler_zyx_to_matrix(*x[6:9]).T
        x_new = np.array(x, dtype=float)
        x_new[0:3] = _vec3(p_nav_m, "p_nav_m")
        x_new[3:6] = turn @ x_new[3:6]
        x_new[6:9] = psi
        return x_new


# ----------------------------------------------------------------------------- several steps


def _check_inputs(model: MotionModel, x: F64, U: F64, dts: F64) -> tuple[F64, F64, list[float]]:
    x = np.array(x, dtype=float).reshape(-1)
    if x.shape != (model.n,):
        raise ValueError(f"{model.kind} state: expected {model.n} numbers, got {x.shape}")
    dt = np.asarray(dts, dtype=float).reshape(-1)
    K = dt.shape[0]
    U = np.asarray(U, dtype=float)
    if model.input_size == 0 and U.size == 0:
        U = np.zeros((K, 0))
    if U.shape != (K, model.input_size):
        raise ValueError(
            f"{model.kind} inputs: expected shape ({K}, {model.input_size}) for {K} steps, "
            f"got {U.shape}"
        )
    if not np.all(np.isfinite(dt)) or np.any(dt < 0):
        raise ValueError("time steps: expected finite values >= 0")
    return x, U, dt.tolist()


def propagate(model: MotionModel, x: F64, U: F64, dts: F64) -> tuple[F64, F64, F64]:
    """Apply K steps: U (K, input_size) inputs, dts (K,) s, U[k] held over dts[k].

    Returns (x_K (n,), F_total (n, n) = F_K ... F_1, Q_total (n, n)) with Q_0 = 0,
    Q_k = F_k Q_{k-1} F_k^T + Q_step,k, so that for any P, F_total P F_total^T + Q_total is
    the covariance after the K predictions (P <- F P F^T + Q one by one). A filter applies it
    once per camera frame: P_vv <- F P_vv F^T + Q, P_vm <- F P_vm (static landmarks, eq. 1).
    K = 0 gives (x, I, 0).
    """
    x, U, dt = _check_inputs(model, x, U, dts)
    n = model.n
    if not dt:
        return x, np.eye(n), np.zeros((n, n))
    x, F_total, Q_total = model.step(x, U[0], dt[0])
    for k in range(1, len(dt)):
        x, F, Q = model.step(x, U[k], dt[k])
        F_total = F @ F_total
        Q_total = F @ Q_total @ F.T + Q
    return x, F_total, 0.5 * (Q_total + Q_total.T)
