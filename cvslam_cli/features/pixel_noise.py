"""The keypoints' pixel noise, measured from the frames' own motion: the filter's
observation noise R where `fuse.association.pixel_sigma_px` is auto.

The filter models each pixel coordinate of a stereo observation (u_l, v_l, u_r, v_r) as
independent Gaussian noise of one sigma. What that sigma is depends on the images (blur,
texture, resolution) and the detector, so it is measured, not guessed: in consecutive frame
pairs (`frame_pairs.py`: stereo points re-found by descriptor, the pair's motion from PnP with
RANSAC, refined by a robust least squares of the whitened residuals below), each re-found
point's earlier (u, v, d) predicts its later one, and the residual r (3,) has, under that
model,

    Cov(r) = sigma^2 (J U J^T + U),    U = [[1, 0, 1], [0, 1, 0], [1, 0, 2]]

(U: the covariance of (u, v, d = u_l - u_r) for unit noise per coordinate; J (3, 3): the
prediction's derivative with respect to the earlier (u, v, d), which carries the earlier
point's depth noise into the later frame). So q = r^T (J U J^T + U)^-1 r / sigma^2 is
chi-square with 3 degrees of freedom, and sigma follows from the q's.

Which sigma: SIFT's errors are not Gaussian. Their core is narrow and their tail long
(simulated images: the median gives 0.15 px, the RMS 0.7 px; KITTI: 0.21 and 1.5 px), and a
Gaussian fitted to the core makes the filter believe the tail (its chi-square tests admit it
as 5-10 sigma information). The filter's tests decide in the tail, so the sigma is the one
whose Gaussian puts the same share of the points inside its `QUANTILE` region as the data:
sigma^2 = quantile_0.95(q_unit) / chi2_3.ppf(0.95). On Gaussian noise it is that noise
(landmark-mode simulation: 0.51 px for a true 0.5); measured values and what they do to the
filter: BENCHMARKS.md, "Fuse: consistency (issue 15)", eleventh step.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from cvslam_cli.features.frame_pairs import (
    RectifiedIntrinsics,
    moved,
    pair_ks,
    pnp_inliers,
    points,
    predicted_uvd,
    refound,
)
from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.features import FeatureSet

# The share of re-found points the fitted Gaussian covers as the data do (module docstring).
QUANTILE = 0.95
# Huber threshold (px, of the whitened residual) of each pair's motion, fitted in this many
# rounds of whitening at the motion of the round before.
HUBER_PX = 1.0
WHITENING_ROUNDS = 3
# Fewer re-found points than this (over all pairs) measure nothing.
MIN_POINTS = 100
# (u, v, d) covariance for unit noise on each of u_l, v_l, u_r, v_r (d = u_l - u_r)
UNIT_UVD = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 2.0]])


@dataclass(frozen=True, eq=False)
class NoiseSample:
    """What one vehicle's frames say about the pixel noise: `q_unit` (n,) each re-found
    point's squared residual whitened for unit noise per pixel coordinate (module
    docstring), from `pairs` frame pairs."""

    q_unit: F64
    pairs: int

    @property
    def points(self) -> int:
        return len(self.q_unit)


@dataclass(frozen=True)
class PixelNoise:
    """sigma_px: per pixel coordinate (module docstring); also the median-based sigma of the
    core (`core_sigma_px`), and the frame pairs and points measured."""

    sigma_px: float
    core_sigma_px: float
    pairs: int
    points: int


def sample_pixel_noise(fs: FeatureSet, rig: StereoRig, max_pairs: int = 100) -> NoiseSample:
    """The residuals of `fs`'s re-found points (at most `max_pairs` consecutive frame pairs
    spread over the log; none for a rig that is not rectified or a single frame)."""
    if not rig.rectified or fs.n_frames < 2:
        return NoiseSample(np.zeros(0), 0)
    K = RectifiedIntrinsics.of(rig)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    qs = []
    for k in pair_ks(fs, max_pairs):
        found = refound(fs, int(k), K, matcher)
        inl = None if found is None else pnp_inliers(*found, K)
        if found is None or inl is None:
            continue
        rows, motion0 = inl
        qs.append(_whitened_residuals(found[0][rows], found[1][rows], motion0, K))
    return NoiseSample(np.concatenate(qs) if qs else np.zeros(0), len(qs))


def pixel_noise(samples: list[NoiseSample]) -> PixelNoise | None:
    """The sigma of the samples pooled (module docstring); None with fewer than MIN_POINTS
    points."""
    q = np.concatenate([s.q_unit for s in samples]) if samples else np.zeros(0)
    if len(q) < MIN_POINTS:
        return None
    return PixelNoise(
        sigma_px=float(np.sqrt(np.quantile(q, QUANTILE) / chi2.ppf(QUANTILE, 3))),
        core_sigma_px=float(np.sqrt(np.median(q) / chi2.median(3))),
        pairs=sum(s.pairs for s in samples),
        points=len(q),
    )


def _whitened_residuals(uvd0: F64, uvd1: F64, motion0: F64, K: RectifiedIntrinsics) -> F64:
    """(n,) r^T C^-1 r, C = J U J^T + U, of one pair's points at its motion fitted to the
    whitened residuals (maximum likelihood; plain residuals would let the motion absorb the
    earlier points' depth noise: over flat ground a turn and a sideways step look alike),
    C re-evaluated at the motion `WHITENING_ROUNDS` times."""
    motion = motion0
    for _ in range(WHITENING_ROUNDS):
        C = _residual_covariance(uvd0, motion, K)
        L_inv = np.linalg.inv(np.linalg.cholesky(C))

        def whitened(m: F64, L_inv: F64 = L_inv) -> F64:
            r = predicted_uvd(moved(uvd0, m, K), K) - uvd1
            return np.einsum("nij,nj->ni", L_inv, r).ravel()

        motion = least_squares(whitened, motion, loss="huber", f_scale=HUBER_PX, x_scale="jac").x
    r = predicted_uvd(moved(uvd0, motion, K), K) - uvd1
    C = _residual_covariance(uvd0, motion, K)
    return np.einsum("ni,ni->n", r, np.linalg.solve(C, r[..., None])[..., 0])


def _residual_covariance(uvd0: F64, motion: F64, K: RectifiedIntrinsics) -> F64:
    """(n, 3, 3) C = J U J^T + U for unit pixel noise (module docstring)."""
    J = prediction_jacobian(uvd0, motion, K)
    return J @ UNIT_UVD @ np.swapaxes(J, 1, 2) + UNIT_UVD


def prediction_jacobian(uvd0: F64, motion: F64, K: RectifiedIntrinsics) -> F64:
    """(n, 3, 3): d (later (u, v, d)) / d (earlier (u, v, d)) of `frame_pairs.predicted_uvd`
    after `moved` with one motion (6,)."""
    R = Rotation.from_rotvec(motion[:3]).as_matrix()
    u, v, _ = uvd0.T
    X = points(uvd0, K)
    z = X[:, 2]
    n = len(uvd0)
    dX = np.zeros((n, 3, 3))  # d X / d (u, v, d)
    dz_dd = -(z**2) / K.fb
    dX[:, 0, 0] = z / K.f
    dX[:, 1, 1] = z / K.fy
    dX[:, 0, 2] = (u - K.cx) / K.f * dz_dd
    dX[:, 1, 2] = (v - K.cy) / K.fy * dz_dd
    dX[:, 2, 2] = dz_dd
    Y = X @ R.T + motion[3:]  # `moved`, from the points and rotation at hand
    dP = np.zeros((n, 3, 3))  # d (u, v, d) / d Y
    dP[:, 0, 0] = K.f / Y[:, 2]
    dP[:, 0, 2] = -K.f * Y[:, 0] / Y[:, 2] ** 2
    dP[:, 1, 1] = K.fy / Y[:, 2]
    dP[:, 1, 2] = -K.fy * Y[:, 1] / Y[:, 2] ** 2
    dP[:, 2, 2] = -K.fb / Y[:, 2] ** 2
    return dP @ R @ dX
