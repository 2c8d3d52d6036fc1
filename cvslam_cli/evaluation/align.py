"""Trajectory alignment (Umeyama 1991), as evo's `--align` / `--correct_scale` do.

Given matched positions of an estimate `est` (N, 3) and the reference `ref` (N, 3), find the
rotation R, translation t and (for sim3) scale s minimising sum |ref_i - (s R est_i + t)|^2:
with the centred point sets and the SVD of their cross-covariance
Sigma = (1/N) sum (ref_i - mu_ref)(est_i - mu_est)^T = U D V^T,

    R = U S V^T  (S = diag(1, 1, det(U V^T)), a proper rotation),
    s = trace(D S) / sigma_est^2  (sim3; 1 for se3),   t = mu_ref - s R mu_est.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cvslam_cli.records.arrays import F64


@dataclass(frozen=True, eq=False)
class Alignment:
    """p_ref = scale * R @ p_est + t. R (3, 3), t (3,)."""

    R: F64
    t: F64
    scale: float

    def apply(self, p: F64) -> F64:
        """Map (N, 3) estimate positions into the reference frame."""
        return self.scale * np.asarray(p, dtype=float) @ self.R.T + self.t


IDENTITY = Alignment(np.eye(3), np.zeros(3), 1.0)


def umeyama(est: F64, ref: F64, kind: Literal["se3", "sim3"] = "se3") -> Alignment:
    """The least-squares similarity (sim3) or rigid (se3) transform taking est onto ref."""
    est = np.asarray(est, dtype=float)
    ref = np.asarray(ref, dtype=float)
    if est.shape != ref.shape or est.ndim != 2 or est.shape[1] != 3 or len(est) < 3:
        raise ValueError(f"need two (N, 3) arrays with N >= 3, got {est.shape} and {ref.shape}")
    mu_e, mu_r = est.mean(axis=0), ref.mean(axis=0)
    e, r = est - mu_e, ref - mu_r
    U, D, Vt = np.linalg.svd(r.T @ e / len(est))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = (
        float(np.trace(np.diag(D) @ S) / np.mean(np.sum(e * e, axis=1))) if kind == "sim3" else 1.0
    )
    return Alignment(R, mu_r - scale * R @ mu_e, scale)
