"""Measurement updates of the EKF and of the nonlinear H-infinity filter (DESIGN.md section 2).

Both take the predicted state x (n,), covariance P (n, n), measurement y (m,), predicted
measurement h (m,), Jacobian H (m, n) and noise covariance R (m, m); the H-infinity filter
uses the scaled R_hat = c_v^2 R (the caller scales) and a bound gamma on a chosen set of
states (indices `bounded`, the matrix L selecting them; all states when None):

    K  = P H^T (H P H^T + R_hat)^-1,   x+ = x + K (y - h)
    S  = [[L P L^T - gamma^2 I, L P H^T], [H P L^T, H P H^T + R_hat]]
    P+ = P - P [L^T H^T] S^-1 [L; H] P

which exists only while P^-1 + H^T R_hat^-1 H - gamma^-2 L^T L is positive definite, i.e.
(with P_ekf = (P^-1 + H^T R_hat^-1 H)^-1, the EKF posterior) while the largest eigenvalue
of L P_ekf L^T is below gamma^2. When it is not, gamma is raised to
sqrt((1 + margin) * lambda_max) for this update and the result says so: the filter never
produces a covariance that is not positive definite. As gamma -> infinity S^-1 keeps only
its EKF corner and P+ is the EKF posterior (a test, not an assumption).

With L selecting the vehicle states (l of them), every product is n x (l + m): the update
costs O(n^2 (l + m)), not O(n^3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """x (n,), P (n, n); nis: normalised innovation squared; gamma: the bound used;
    gamma_raised: the existence condition failed with the configured gamma."""

    x: F64
    P: F64
    nis: float
    gamma: float = float("inf")
    gamma_raised: bool = False


def _innovation(P: F64, H: F64, R: F64, y: F64, h: F64) -> tuple[F64, F64, F64, float]:
    PHt = P @ H.T
    S = H @ PHt + R
    nu = y - h
    S_inv_nu = np.linalg.solve(S, nu)
    return PHt, S, nu, float(nu @ S_inv_nu)


def ekf_update(x: F64, P: F64, y: F64, h: F64, H: F64, R: F64) -> UpdateResult:
    """EKF update, Joseph form P+ = (I - K H) P (I - K H)^T + K R K^T."""
    PHt, S, nu, nis = _innovation(P, H, R, y, h)
    K = np.linalg.solve(S, PHt.T).T
    A = np.eye(len(x)) - K @ H
    P_new = A @ P @ A.T + K @ R @ K.T
    return UpdateResult(x + K @ nu, 0.5 * (P_new + P_new.T), nis)


def hinf_update(
    x: F64,
    P: F64,
    y: F64,
    h: F64,
    H: F64,
    R_hat: F64,
    gamma: float,
    bounded: I64 | None = None,
    margin: float = 0.1,
) -> UpdateResult:
    """Nonlinear H-infinity update (module docstring); `bounded`: indices of the states the
    bound is put on (None: all)."""
    n = len(x)
    idx = np.arange(n) if bounded is None else np.asarray(bounded, dtype=np.int64)
    l_dim = len(idx)
    PHt, S_y, nu, nis = _innovation(P, H, R_hat, y, h)
    K = np.linalg.solve(S_y, PHt.T).T
    # existence: lambda_max(L P_ekf L^T) < gamma^2, P_ekf = P - K H P (only its L block)
    P_ekf_LL = P[np.ix_(idx, idx)] - K[idx] @ PHt[idx].T
    lam = float(np.linalg.eigvalsh(0.5 * (P_ekf_LL + P_ekf_LL.T))[-1])
    raised = np.isfinite(gamma) and lam >= gamma**2 / (1.0 + margin)
    if raised:
        gamma = float(np.sqrt((1.0 + margin) * lam))
    if not np.isfinite(gamma):
        P_new = P - K @ PHt.T
        return UpdateResult(x + K @ nu, 0.5 * (P_new + P_new.T), nis, gamma, False)
    W = np.concatenate([P[:, idx], PHt], axis=1)  # P [L^T H^T], (n, l + m)
    Sigma = np.empty((l_dim + len(y), l_dim + len(y)))
    Sigma[:l_dim, :l_dim] = P[np.ix_(idx, idx)] - gamma**2 * np.eye(l_dim)
    Sigma[:l_dim, l_dim:] = PHt[idx]
    Sigma[l_dim:, :l_dim] = PHt[idx].T
    Sigma[l_dim:, l_dim:] = S_y
    P_new = P - W @ np.linalg.solve(Sigma, W.T)
    return UpdateResult(x + K @ nu, 0.5 * (P_new + P_new.T), nis, gamma, bool(raised))
