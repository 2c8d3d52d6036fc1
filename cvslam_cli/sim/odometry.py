"""Simulated wheel odometry of a ground robot (what a node publishes as nav_msgs/Odometry).

The robot measures its forward speed v (body x) and yaw rate ω_z (body z, FRD: positive turns
right, i.e. from north towards east) and dead-reckons a planar pose (x, y, ψ) in the odom frame,
which here starts at the true initial pose so that odom and nav coincide at t0:
    ẋ = v cos ψ,   ẏ = v sin ψ,   ψ̇ = ω_z
(the 3-DOF subset of the paper's process model, eq. 1, for ground robots).

Error model ("drift and noise" added artificially, as in the paper's experiments):
    ṽ_k = (1 + speed_scale_error) v_k + n_v,k          n_v ~ N(0, (speed_noise_density √rate)²)
    ω̃_k = ω_k + yaw_rate_bias_rad_s + n_ω,k           n_ω ~ N(0, (yaw_rate_noise_density √rate)²)
A scale error makes the distance drift proportionally; a yaw-rate bias bends the path
(position error growing like v b t² / 2).

Integration between samples: the measured speed and yaw rate are interpolated by the local cubic
through neighbouring samples (`local_cubic_coefficients`); ψ is its exact integral (a quartic in
time) and x, y are integrated with 6-point Gauss-Legendre per interval, so noise-free data
reproduce the true planar pose to ~1e-9 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64
from cvslam_cli.sim.imu import check_times, white_noise_sigma
from cvslam_cli.sim.strapdown import local_cubic_coefficients
from cvslam_cli.sim.trajectory import Trajectory


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel-odometry errors.

    speed_scale_error: dimensionless, measured speed = (1 + e) × true speed (0.02: 2 % drift).
    yaw_rate_bias_rad_s: constant yaw-rate bias, rad/s.
    speed_noise_density: white noise on the speed, m/s/√Hz.
    yaw_rate_noise_density: white noise on the yaw rate, rad/s/√Hz.
    """

    speed_scale_error: float = 0.02
    yaw_rate_bias_rad_s: float = 0.005
    speed_noise_density: float = 0.01
    yaw_rate_noise_density: float = 0.002

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"odometry noise {name} must be finite, got {value}")
        if self.speed_scale_error <= -1.0:
            raise ValueError(f"speed_scale_error must be > -1, got {self.speed_scale_error}")
        if self.speed_noise_density < 0 or self.yaw_rate_noise_density < 0:
            raise ValueError("odometry noise densities must be >= 0")


@dataclass(frozen=True, eq=False)
class OdometryData:
    """Simulated odometry, N samples.

    t_s: (N,) seconds.
    v_forward_m_s: (N,) measured forward speed (body x).
    yaw_rate_rad_s: (N,) measured yaw rate (body z, FRD).
    x_m, y_m: (N,) dead-reckoned position in the odom frame (= nav north, east at t0).
    yaw_rad: (N,) dead-reckoned heading, wrapped to (-pi, pi].
    """

    t_s: F64
    v_forward_m_s: F64
    yaw_rate_rad_s: F64
    x_m: F64
    y_m: F64
    yaw_rad: F64


def dead_reckon_planar(
    t_s: F64, v_forward_m_s: F64, yaw_rate_rad_s: F64, x0_m: float, y0_m: float, yaw0_rad: float
) -> tuple[F64, F64, F64]:
    """Integrate ẋ = v cos ψ, ẏ = v sin ψ, ψ̇ = ω (see module docstring); returns (x, y, ψ)."""
    t = check_times(t_s)
    v = np.asarray(v_forward_m_s, dtype=float).reshape(-1)
    w = np.asarray(yaw_rate_rad_s, dtype=float).reshape(-1)
    if v.shape != t.shape or w.shape != t.shape:
        raise ValueError(f"speed and yaw rate must be {t.shape} like t_s")
    if t.size == 1:
        return np.array([x0_m]), np.array([y0_m]), np.array([yaw0_rad])
    dt = np.diff(t)
    cv = local_cubic_coefficients(t, v)  # (N-1, m) in u = (t - t_k)/dt
    cw = local_cubic_coefficients(t, w)
    powers = np.arange(cw.shape[1])
    # ψ(u) = ψ_k + dt Σ_j cw_j u^{j+1} / (j + 1)
    dpsi = dt * np.sum(cw / (powers + 1), axis=1)
    psi = yaw0_rad + np.concatenate([[0.0], np.cumsum(dpsi)])
    ug, wg = np.polynomial.legendre.leggauss(6)
    ug, wg = 0.5 * (ug + 1.0), 0.5 * wg  # on [0, 1]
    up = ug[None, :] ** powers[:, None]  # (m, G)
    upi = ug[None, :] ** (powers[:, None] + 1) / (powers[:, None] + 1)
    v_g = cv @ up  # (N-1, G)
    psi_g = psi[:-1, None] + dt[:, None] * (cw @ upi)
    dx = dt * np.sum(wg * v_g * np.cos(psi_g), axis=1)
    dy = dt * np.sum(wg * v_g * np.sin(psi_g), axis=1)
    x = x0_m + np.concatenate([[0.0], np.cumsum(dx)])
    y = y0_m + np.concatenate([[0.0], np.cumsum(dy)])
    return x, y, np.angle(np.exp(1j * psi))


def simulate_odometry(
    traj: Trajectory,
    t_s: F64,
    noise: OdometryNoise | None,
    rng: np.random.Generator | None,
) -> OdometryData:
    """Odometry at `t_s` (N,) along a ground-robot trajectory; `noise=None` gives exact values.

    True inputs: v = (C_nav_body^T v^n)_x and ω_z = ω^b_z (for a level robot ω_z = ψ̇).
    Dead reckoning starts at the true (x, y, ψ) at t_s[0].
    """
    t = check_times(t_s)
    m = traj.sample(t)
    v_true = m.v_body_m_s[:, 0]
    w_true = m.omega_body_rad_s[:, 2]
    if noise is None:
        v_meas, w_meas = v_true.copy(), w_true.copy()
    else:
        if rng is None:
            raise ValueError("a numpy.random.Generator is needed to simulate odometry noise")
        s_v = white_noise_sigma(t, noise.speed_noise_density)
        s_w = white_noise_sigma(t, noise.yaw_rate_noise_density)
        v_meas = (1.0 + noise.speed_scale_error) * v_true + s_v * rng.standard_normal(t.size)
        w_meas = w_true + noise.yaw_rate_bias_rad_s + s_w * rng.standard_normal(t.size)
    x, y, yaw = dead_reckon_planar(
        t, v_meas, w_meas, m.p_nav_m[0, 0], m.p_nav_m[0, 1], m.euler_rad[0, 2]
    )
    return OdometryData(t, v_meas, w_meas, x, y, yaw)
