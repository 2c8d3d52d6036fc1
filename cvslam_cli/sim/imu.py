"""Simulated IMU: exact specific force and angular rate, plus a standard MEMS error model.

The IMU measures, in body (FRD) axes, the inputs of the paper's INS process model (eq. 1-2):
    ω^b = angular rate of body w.r.t. nav (the earth's rotation is neglected, as in the paper)
    f^b = C^b_n (a^n − g^n)       (specific force: what an accelerometer at rest reads is −g)
With NED gravity g^n = (0, 0, +9.80665) m/s², a level IMU at rest reads f^b = (0, 0, −9.80665).

Error model (Kalibr / EuRoC convention, continuous-time densities):
    ω̃_k = ω_k + b_g,k + n_g,k        n_g,k ~ N(0, σ_g² I),   σ_g = gyro_noise_density · √rate
    f̃_k = f_k + b_a,k + n_a,k        n_a,k ~ N(0, σ_a² I),   σ_a = accel_noise_density · √rate
    b_k = b_{k-1} + σ_rw √Δt_k · w_k  (bias random walk, σ_rw = *_random_walk)
    b_0 ~ N(0, *_bias_initial_sigma² I)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.geometry.gravity import G_NAV_M_S2
from cvslam_cli.records.arrays import F64, check_increasing
from cvslam_cli.sim.trajectory import MotionSample, Trajectory


@dataclass(frozen=True)
class ImuNoise:
    """IMU error parameters. Defaults: the ADIS16448 of the EuRoC MAV datasets.

    gyro_noise_density: rad/s/√Hz (white noise), EuRoC sensor.yaml 1.6968e-4.
    gyro_random_walk: rad/s²/√Hz (bias diffusion), EuRoC 1.9393e-5.
    accel_noise_density: m/s²/√Hz, EuRoC 2.0e-3.
    accel_random_walk: m/s³/√Hz, EuRoC 3.0e-3.
    gyro_bias_initial_sigma: rad/s, std dev of the turn-on bias per axis. 1e-3 rad/s
        (0.057 °/s) is a typical residual of a calibrated MEMS gyro after start-up.
    accel_bias_initial_sigma: m/s², std dev of the turn-on accelerometer bias per axis.
        2e-2 m/s² (≈ 2 mg) is a typical residual of a calibrated MEMS accelerometer.
    Set a field to 0 to switch that error source off.
    """

    gyro_noise_density: float = 1.6968e-4
    gyro_random_walk: float = 1.9393e-5
    accel_noise_density: float = 2.0e-3
    accel_random_walk: float = 3.0e-3
    gyro_bias_initial_sigma: float = 1.0e-3
    accel_bias_initial_sigma: float = 2.0e-2

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"IMU noise {name} must be a finite value >= 0, got {value}")


@dataclass(frozen=True, eq=False)
class ImuData:
    """Simulated IMU samples.

    t_s: (N,) seconds.
    gyro_rad_s: (N, 3) measured angular rate ω̃^b.
    accel_m_s2: (N, 3) measured specific force f̃^b.
    gyro_bias_rad_s: (N, 3) true gyro bias included in gyro_rad_s.
    accel_bias_m_s2: (N, 3) true accelerometer bias included in accel_m_s2.
    """

    t_s: F64
    gyro_rad_s: F64
    accel_m_s2: F64
    gyro_bias_rad_s: F64
    accel_bias_m_s2: F64


def true_imu(traj_sample: MotionSample, g_nav: F64 = G_NAV_M_S2) -> tuple[F64, F64]:
    """Exact (gyro_rad_s (N, 3), accel_m_s2 (N, 3)): ω^b and f^b = C_nav_body^T (a^n − g^n)."""
    g = np.asarray(g_nav, dtype=float).reshape(3)
    f_body = np.einsum("nji,nj->ni", traj_sample.C_nav_body, traj_sample.a_nav_m_s2 - g)
    return traj_sample.omega_body_rad_s.copy(), f_body


def check_times(t_s: F64) -> F64:
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError(f"t_s must be a non-empty 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("t_s must be finite")
    check_increasing("t_s", t)
    return t


def random_walk(
    t_s: F64, initial_sigma: float, rw_density: float, rng: np.random.Generator, dim: int = 3
) -> F64:
    """(N, dim) b_0 ~ N(0, initial_sigma²), b_k = b_{k-1} + rw_density √Δt_k w_k."""
    b0 = initial_sigma * rng.standard_normal(dim)
    steps = rw_density * np.sqrt(np.diff(t_s))[:, None] * rng.standard_normal((t_s.size - 1, dim))
    return b0[None, :] + np.vstack([np.zeros((1, dim)), np.cumsum(steps, axis=0)])


def white_noise_sigma(t_s: F64, density: float) -> float:
    """Discrete std dev of white noise of `density` (unit/√Hz) sampled at the median rate."""
    if t_s.size < 2:
        raise ValueError("at least 2 samples are needed to know the sampling rate")
    rate_hz = 1.0 / float(np.median(np.diff(t_s)))
    return density * np.sqrt(rate_hz)


def simulate_imu(
    traj: Trajectory,
    t_s: F64,
    noise: ImuNoise | None,
    rng: np.random.Generator | None,
    g_nav: F64 = G_NAV_M_S2,
) -> ImuData:
    """IMU samples at `t_s` (N,) along `traj`; `noise=None` gives the exact values.

    Random draws (in this order: gyro bias, accel bias, gyro noise, accel noise) come from `rng`
    only, so a seeded generator gives identical data.
    """
    t = check_times(t_s)
    gyro, accel = true_imu(traj.sample(t), g_nav)
    zeros = np.zeros_like(gyro)
    if noise is None:
        return ImuData(t, gyro, accel, zeros, zeros.copy())
    if rng is None:
        raise ValueError("a numpy.random.Generator is needed to simulate IMU noise")
    b_g = random_walk(t, noise.gyro_bias_initial_sigma, noise.gyro_random_walk, rng)
    b_a = random_walk(t, noise.accel_bias_initial_sigma, noise.accel_random_walk, rng)
    s_g = white_noise_sigma(t, noise.gyro_noise_density)
    s_a = white_noise_sigma(t, noise.accel_noise_density)
    n_g = s_g * rng.standard_normal(gyro.shape)
    n_a = s_a * rng.standard_normal(accel.shape)
    return ImuData(t, gyro + b_g + n_g, accel + b_a + n_a, b_g, b_a)
