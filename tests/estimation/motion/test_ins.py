"""INS mechanisation (eq. 1): Jacobians equal finite differences; bias states extend the
nine-state model. (Integrating the simulator's noise-free IMU to the truth: test_models.py.)"""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.motion.ins import ins_step_terms


def ins_step(x, accel_m_s2, gyro_rad_s, dt):
    """One step of eq. 1: (x+, F = dx+/dx, G = dx+/d(accel noise, gyro noise[, bias walks]))
    with the white-noise columns of `ins_step_terms`' unit-scaled G multiplied by dt."""
    x_new, F, G = ins_step_terms(x, accel_m_s2, gyro_rad_s, dt)
    G[:, 0:6] *= dt
    return x_new, F, G


@pytest.mark.parametrize("n", [9, 15])
def test_jacobians_equal_finite_differences(n):
    rng = np.random.default_rng(2)
    x = np.concatenate([[5.0, -3.0, -80.0], [9.0, 0.5, -0.3], [0.1, -0.2, 1.3]])
    if n == 15:
        x = np.concatenate([x, rng.normal(0, 0.05, 3), rng.normal(0, 0.01, 3)])
    f, w, dt = np.array([0.3, -0.2, -9.7]), np.array([0.02, -0.05, 0.1]), 0.005
    _, F, G = ins_step(x, f, w, dt)
    h = 1e-6
    for k in range(n):
        d = np.zeros(n)
        d[k] = h
        fd = (ins_step(x + d, f, w, dt)[0] - ins_step(x - d, f, w, dt)[0]) / (2 * h)
        np.testing.assert_allclose(F[:, k], fd, atol=1e-8)
    # noise inputs: accelerometer and gyro noise act like errors of f and w
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd_a = (ins_step(x, f + d, w, dt)[0] - ins_step(x, f - d, w, dt)[0]) / (2 * h)
        fd_g = (ins_step(x, f, w + d, dt)[0] - ins_step(x, f, w - d, dt)[0]) / (2 * h)
        np.testing.assert_allclose(G[:, k], fd_a, atol=1e-8)
        np.testing.assert_allclose(G[:, 3 + k], fd_g, atol=1e-8)


def test_bias_states_with_zero_bias_match_the_nine_state_model():
    x9 = np.concatenate([[5.0, -3.0, -80.0], [9.0, 0.5, -0.3], [0.1, -0.2, 1.3]])
    x15 = np.concatenate([x9, np.zeros(6)])
    f, w, dt = np.array([0.3, -0.2, -9.7]), np.array([0.02, -0.05, 0.1]), 0.005
    x9_new, F9, G9 = ins_step(x9, f, w, dt)
    x15_new, F15, G15 = ins_step(x15, f, w, dt)
    np.testing.assert_array_equal(x15_new[:9], x9_new)
    np.testing.assert_array_equal(F15[:9, :9], F9)
    np.testing.assert_array_equal(G15[:9, :6], G9)
    np.testing.assert_array_equal(x15_new[9:], 0.0)
    with pytest.raises(ValueError, match="expected 9 or 15 numbers"):
        ins_step(x9[:6], f, w, dt)
