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

import math
from dataclasses import dataclass

import numpy as np

from cvslam_cli.geometry.gravity import G_NAV_M_S2
from cvslam_cli.records.arrays import F64


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


def _block_indices(n: int, blocks: list[tuple[int, int, int, int]]) -> np.ndarray:
    """Flat indices into an (n, m) row-major matrix of the blocks (row0, col0, rows, cols),
    each block row-major, blocks in order; `n` here is the number of columns."""
    idx: list[int] = []
    for r0, c0, nr, nc in blocks:
        idx += [(r0 + i) * n + c0 + j for i in range(nr) for j in range(nc)]
    return np.array(idx, dtype=np.intp)


# Entries of F and G that change from step to step (the rest is the constant template).
_F_BLOCKS = [(0, 3, 3, 3), (0, 6, 3, 3), (3, 3, 3, 3), (3, 6, 3, 3), (6, 6, 3, 3)]
_F_BIAS_BLOCKS = [(3, 12, 3, 3), (6, 12, 3, 3)]
_F_IDX = {9: _block_indices(9, _F_BLOCKS), 15: _block_indices(15, _F_BLOCKS + _F_BIAS_BLOCKS)}
_G_BLOCKS = [(3, 3, 3, 3), (6, 3, 3, 3)]  # accelerometer-noise block (3:6, 0:3) is dt I
_G_IDX = {9: _block_indices(6, _G_BLOCKS), 15: _block_indices(12, _G_BLOCKS)}


def _templates(n: int) -> tuple[F64, F64]:
    """Constant parts: F0 (n, n) the identity, G0 (n, n_noise) the identity blocks of the
    accelerometer noise (unit-scaled) and of the bias walks."""
    F0 = np.eye(n)
    n_noise = 12 if n == 15 else 6
    G0 = np.zeros((n, n_noise))
    G0[3:6, 0:3] = np.eye(3)
    if n == 15:
        G0[9:12, 6:9] = np.eye(3)
        G0[12:15, 9:12] = np.eye(3)
    return F0, G0


_TEMPLATES = {9: _templates(9), 15: _templates(15)}


def ins_step_terms(
    x: F64, accel_m_s2: F64, gyro_rad_s: F64, dt: float, g_nav: F64 = G_NAV_M_S2
) -> tuple[F64, F64, F64]:
    """One step of eq. 1-2 for a 9- or 15-state vehicle: (x+ (n,), F (n, n) = dx+/dx,
    Gu (n, n_noise)), where Gu is dx+/d(noise) with the white-noise columns divided by dt
    (so G = Gu for the bias walks and G = Gu dt for the sensor noise; Gu stays finite as
    dt -> 0). n_noise = 6 (accel, gyro noise) or 12 (+ accel, gyro bias walks).

    Written on Python floats (no 3x3 numpy products): at 200 Hz numpy's per-call overhead,
    not arithmetic, would dominate.
    """
    n = x.shape[0]
    if n not in (9, 15):
        raise ValueError(f"INS state: expected 9 or 15 numbers, got {n}")
    xl = x.tolist()
    f0, f1, f2 = np.asarray(accel_m_s2, dtype=float).tolist()
    w0, w1, w2 = np.asarray(gyro_rad_s, dtype=float).tolist()
    g0, g1, g2 = np.asarray(g_nav, dtype=float).tolist()
    p0, p1, p2, v0, v1, v2, roll, pitch, yaw = xl[:9]
    if n == 15:
        f0, f1, f2 = f0 - xl[9], f1 - xl[10], f2 - xl[11]
        w0, w1, w2 = w0 - xl[12], w1 - xl[13], w2 - xl[14]
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    # C_nav_body = Rz(yaw) Ry(pitch) Rx(roll) (paper's C^n_b)
    C00, C01, C02 = cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy
    C10, C11, C12 = cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy
    C20, C21, C22 = -sp, sr * cp, cr * cp
    Cv0 = C00 * v0 + C01 * v1 + C02 * v2
    Cv1 = C10 * v0 + C11 * v1 + C12 * v2
    Cv2 = C20 * v0 + C21 * v1 + C22 * v2
    Cg0 = C00 * g0 + C10 * g1 + C20 * g2  # C^T g
    Cg1 = C01 * g0 + C11 * g1 + C21 * g2
    Cg2 = C02 * g0 + C12 * g1 + C22 * g2
    # E(Psi): Euler rates from body rates
    sec = 1.0 / cp
    tp = sp * sec
    a = sr * w1 + cr * w2
    b = cr * w1 - sr * w2
    xn = list(xl)
    # eq. 1: p+ = p + C v dt;  v+ = v + (f + v x w + C^T g) dt;  Psi+ = Psi + E w dt
    xn[0] = p0 + Cv0 * dt
    xn[1] = p1 + Cv1 * dt
    xn[2] = p2 + Cv2 * dt
    xn[3] = v0 + (f0 + v1 * w2 - v2 * w1 + Cg0) * dt
    xn[4] = v1 + (f1 + v2 * w0 - v0 * w2 + Cg1) * dt
    xn[5] = v2 + (f2 + v0 * w1 - v1 * w0 + Cg2) * dt
    xn[6] = roll + (w0 + tp * a) * dt
    xn[7] = pitch + b * dt
    xn[8] = yaw + a * sec * dt

    # d(C v)/d(roll, pitch, yaw)
    dp_r = (C02 * v1 - C01 * v2, C12 * v1 - C11 * v2, C22 * v1 - C21 * v2)
    aa = -sp * v0 + sr * cp * v1 + cr * cp * v2
    bb = -cp * v0 - sr * sp * v1 - cr * sp * v2
    # d(C^T g)/d(roll, pitch, yaw)
    h = cp * cy * g0 + cp * sy * g1 - sp * g2
    k = -sp * cy * g0 - sp * sy * g1 - cp * g2
    gy0, gy1, gy2 = -C10 * g0 + C00 * g1, -C11 * g0 + C01 * g1, -C12 * g0 + C02 * g1
    E01, E02, E11, E12, E21, E22 = sr * tp, cr * tp, cr, -sr, sr * sec, cr * sec
    d = dt
    vals = [
        # (0:3, 3:6) C dt
        C00 * d, C01 * d, C02 * d, C10 * d, C11 * d, C12 * d, C20 * d, C21 * d, C22 * d,
        # (0:3, 6:9) d(C v)/dPsi dt
        dp_r[0] * d, cy * aa * d, -Cv1 * d,
        dp_r[1] * d, sy * aa * d, Cv0 * d,
        dp_r[2] * d, bb * d, 0.0,
        # (3:6, 3:6) I - [w]x dt  (d(v x w)/dv = -[w]x)
        1.0, w2 * d, -w1 * d, -w2 * d, 1.0, w0 * d, w1 * d, -w0 * d, 1.0,
        # (3:6, 6:9) d(C^T g)/dPsi dt
        0.0, k * d, gy0 * d,
        Cg2 * d, sr * h * d, gy1 * d,
        -Cg1 * d, cr * h * d, gy2 * d,
        # (6:9, 6:9) I + d(E w)/d(roll, pitch) dt
        1.0 + tp * b * d, sec * sec * a * d, 0.0,
        -a * d, 1.0, 0.0,
        sec * b * d, sec * tp * a * d, 1.0,
    ]  # fmt: skip
    if n == 15:
        vals += [
            # (3:6, 12:15) -[v]x dt  (gyro bias enters like -w)
            0.0, v2 * d, -v1 * d, -v2 * d, 0.0, v0 * d, v1 * d, -v0 * d, 0.0,
            # (6:9, 12:15) -E dt
            -d, -E01 * d, -E02 * d, 0.0, -E11 * d, -E12 * d, 0.0, -E21 * d, -E22 * d,
        ]  # fmt: skip
    F0, G0 = _TEMPLATES[n]
    F = F0.copy()
    F.flat[_F_IDX[n]] = vals
    if n == 15:
        F[3, 9] = F[4, 10] = F[5, 11] = -dt  # accelerometer bias enters like -f
    Gu = G0.copy()
    # (3:6, 3:6) [v]x (d(v x w)/dw), (6:9, 3:6) E: gyro noise enters like w
    Gu.flat[_G_IDX[n]] = [
        0.0, -v2, v1, v2, 0.0, -v0, -v1, v0, 0.0,
        1.0, E01, E02, 0.0, E11, E12, 0.0, E21, E22,
    ]  # fmt: skip
    return np.array(xn), F, Gu


def ins_process_noise(noise: InsNoise, dt: float, biases: bool) -> F64:
    """Q of one step for the noise Jacobian G of `ins_step_terms` with its white-noise columns
    scaled by dt (per sample): white noise variance density^2 / dt per sample,
    bias walk variance density^2 * dt."""
    q = [noise.accel_noise_density**2 / dt] * 3 + [noise.gyro_noise_density**2 / dt] * 3
    if biases:
        q += [noise.accel_random_walk**2 * dt] * 3 + [noise.gyro_random_walk**2 * dt] * 3
    return np.diag(q)
