"""Motion models of the filter. This module: the 6-DOF INS mechanisation of the paper (eq. 1),
with optional accelerometer and gyro bias states, and its Jacobians.

State of one vehicle (9, or 15 with biases): p (nav, NED, m), v (body, m/s), Psi (roll, pitch,
yaw, rad) [, b_a (m/s^2), b_g (rad/s)]. With f and w the measured specific force and
angular rate (body), w' = w - b_g, f' = f - b_a, dt the IMU interval (eq. 1, 2):

    p+   = p + C(Psi) v dt
    v+   = v + (f' + v x w' + C(Psi)^T g) dt
    Psi+ = Psi + E(Psi) w' dt
    b+   = b                                     (random walks, driven by process noise)

E maps body rates to ZYX Euler rates. Jacobians are analytic: F = d x+ / d x, G = d x+ / d
(accelerometer noise, gyro noise[, accel bias walk, gyro bias walk]); the process noise of a
step is G Q G^T with Q from the sensor noise densities (white noise density^2 / dt for a
sample, random walk density^2 * dt for a bias).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.rotations import euler_zyx_derivatives, euler_zyx_to_matrix

F64 = NDArray[np.float64]
G_NAV = np.array([0.0, 0.0, 9.80665])


def skew(a: F64) -> F64:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def euler_rate_matrix(euler_rad: F64) -> tuple[F64, F64]:
    """E(Psi) (3, 3) with Psi_dot = E w, and dE/d(roll, pitch) stacked (2, 3, 3)."""
    roll, pitch, _ = euler_rad
    sr, cr, tp, cp = np.sin(roll), np.cos(roll), np.tan(pitch), np.cos(pitch)
    sec = 1.0 / cp
    E = np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr * sec, cr * sec]])
    dE_droll = np.array([[0.0, cr * tp, -sr * tp], [0.0, -sr, -cr], [0.0, cr * sec, -sr * sec]])
    sec2 = sec * sec
    dE_dpitch = np.array(
        [[0.0, sr * sec2, cr * sec2], [0.0, 0.0, 0.0], [0.0, sr * sec * tp, cr * sec * tp]]
    )
    return E, np.stack([dE_droll, dE_dpitch])


@dataclass(frozen=True)
class InsNoise:
    """Densities: white noise (accel m/s^2/sqrt(Hz), gyro rad/s/sqrt(Hz)) and bias random
    walks (accel m/s^3/sqrt(Hz), gyro rad/s^2/sqrt(Hz))."""

    accel_noise_density: float
    gyro_noise_density: float
    accel_random_walk: float = 0.0
    gyro_random_walk: float = 0.0


def ins_step(
    x: F64, accel_m_s2: F64, gyro_rad_s: F64, dt: float, g_nav: F64 = G_NAV
) -> tuple[F64, F64, F64]:
    """One step of eq. 1 for a 9- or 15-state vehicle: (x+, F, G)."""
    n = len(x)
    biases = n == 15
    p, v, psi = x[0:3], x[3:6], x[6:9]
    b_a = x[9:12] if biases else np.zeros(3)
    b_g = x[12:15] if biases else np.zeros(3)
    f = np.asarray(accel_m_s2, dtype=float) - b_a
    w = np.asarray(gyro_rad_s, dtype=float) - b_g
    C = euler_zyx_to_matrix(*psi)
    D = euler_zyx_derivatives(*psi)
    E, dE = euler_rate_matrix(psi)
    x_new = x.copy()
    x_new[0:3] = p + C @ v * dt
    x_new[3:6] = v + (f + np.cross(v, w) + C.T @ g_nav) * dt
    x_new[6:9] = psi + E @ w * dt

    F = np.eye(n)
    F[0:3, 3:6] = C * dt
    F[0:3, 6:9] = np.stack([D[k] @ v for k in range(3)], axis=1) * dt
    F[3:6, 3:6] += -skew(w) * dt  # d (v x w) / d v = -[w]x
    F[3:6, 6:9] = np.stack([D[k].T @ g_nav for k in range(3)], axis=1) * dt
    F[6:9, 6:8] += np.stack([dE[k] @ w for k in range(2)], axis=1) * dt
    n_noise = 12 if biases else 6
    G = np.zeros((n, n_noise))
    G[3:6, 0:3] = np.eye(3) * dt  # accelerometer noise enters like f
    G[3:6, 3:6] = skew(v) * dt  # d (v x w) / d w = [v]x
    G[6:9, 3:6] = E * dt
    if biases:
        F[3:6, 9:12] = -np.eye(3) * dt
        F[3:6, 12:15] = -skew(v) * dt
        F[6:9, 12:15] = -E * dt
        G[9:12, 6:9] = np.eye(3)
        G[12:15, 9:12] = np.eye(3)
    return x_new, F, G


def ins_process_noise(noise: InsNoise, dt: float, biases: bool) -> F64:
    """Q of one step for `ins_step`'s G: white noise variance density^2 / dt per sample,
    bias walk variance density^2 * dt."""
    q = [noise.accel_noise_density**2 / dt] * 3 + [noise.gyro_noise_density**2 / dt] * 3
    if biases:
        q += [noise.accel_random_walk**2 * dt] * 3 + [noise.gyro_random_walk**2 * dt] * 3
    return np.diag(q)
