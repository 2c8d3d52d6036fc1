"""Guided matching in one keyframe (pure numpy): predict points into both images of the
stereo pair with the current pose (eq. 19: u_c = K_c p_c / z_c, p_c the point in camera c's
optical frame), take the keyframe's stereo matches inside a pixel gate around each
prediction, and keep a pair when its descriptor passes the ratio test among the candidates
of that gate (the paper's descriptor test, before eq. 20, now in a window the pose gives).

The gate is on the whole stereo measurement, |z - z_hat|^2 over (u_l, v_l, u_r, v_r) below
r^2: both cameras at once, so a match must agree in the left image and in its disparity. A
point's descriptor distance is the smallest over the descriptors it was seen with (a set per
point: the appearance changes along a track). A match claimed by several points goes to the
smallest distance, a point takes at most one match.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.records.arrays import F64, I64, U8, BoolArray

# descriptor pairs per block of the set distances (bounded temporary memory)
_PAIR_BLOCK = 20000


@dataclass(frozen=True, eq=False)
class Matches:
    """n accepted (point, feature) pairs: `point` (n,) and `feature` (n,) rows of the
    inputs, `distance` (n,) descriptor distance, `d2_px` (n,) squared pixel distance of the
    measurement from the prediction (4 coordinates)."""

    point: I64
    feature: I64
    distance: F64
    d2_px: F64

    @staticmethod
    def empty() -> Matches:
        e = np.zeros(0, dtype=np.int64)
        return Matches(e, e.copy(), np.zeros(0), np.zeros(0))

    def __len__(self) -> int:
        return len(self.point)


def project(T_nav_body: F64, K_px: F64, T_body_cam: F64, p_nav_m: F64) -> tuple[F64, F64]:
    """Points p_nav_m (L, 3) seen from pose T_nav_body (4, 4) by the cameras K_px (2, 3, 3),
    T_body_cam (2, 4, 4): (z (L, 4) = (u_l, v_l, u_r, v_r), depth (L, 2) along each optical
    axis) (eq. 19)."""
    p = np.asarray(p_nav_m, dtype=float).reshape(-1, 3)
    z = np.empty((len(p), 4))
    depth = np.empty((len(p), 2))
    for c in range(2):
        T_nav_cam = T_nav_body @ T_body_cam[c]
        p_cam = (p - T_nav_cam[:3, 3]) @ T_nav_cam[:3, :3]  # R^T (p - t) per row
        depth[:, c] = p_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = p_cam @ K_px[c].T
            z[:, 2 * c : 2 * c + 2] = uvw[:, :2] / uvw[:, 2:3]
    return z, depth


def in_images(
    z: F64, depth: F64, size_px: NDArray[np.int64], min_depth_m: float = 0.1
) -> BoolArray:
    """(L,) in front of both cameras (depth above min_depth_m) and inside both images."""
    ok = np.all(depth > min_depth_m, axis=1)
    for c in range(2):
        w, h = size_px[c]
        u, v = z[:, 2 * c], z[:, 2 * c + 1]
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return ok


def set_distances(desc_sets: U8, n_desc: I64, point: I64, desc: U8, feature: I64) -> F64:
    """(P,) the descriptor distance of each (point, feature) pair: the smallest Euclidean
    distance between the feature's descriptor desc[feature] (D,) and the point's set
    desc_sets[point, :n_desc[point]] ((L, S, D) uint8, n_desc (L,) >= 1)."""
    out = np.empty(len(point))
    S = desc_sets.shape[1]
    for s in range(0, len(point), _PAIR_BLOCK):
        pi, fi = point[s : s + _PAIR_BLOCK], feature[s : s + _PAIR_BLOCK]
        diff = desc_sets[pi].astype(np.float32) - desc[fi].astype(np.float32)[:, None, :]
        d = np.sqrt(np.einsum("psd,psd->ps", diff, diff))  # (p, S)
        d[np.arange(S)[None, :] >= n_desc[pi][:, None]] = np.inf
        out[s : s + _PAIR_BLOCK] = d.min(axis=1)
    return out


def match(
    z_pred: F64,
    desc_sets: U8,
    n_desc: I64,
    z_obs: F64,
    desc_obs: U8,
    radius_px: float | F64,
    ratio: float,
    max_distance: float,
) -> Matches:
    """Guided matching of k predicted points (z_pred (k, 4), descriptor sets (k, S, D) with
    n_desc (k,)) with M features (z_obs (M, 4), desc_obs (M, D)) inside the gate
    |z - z_hat| < radius_px (scalar or (k,)) (module docstring). A point passes the ratio test
    when its best distance D1 < ratio * D2 (second best in its gate; a lone candidate has none)
    and D1 < max_distance."""
    k, M = len(z_pred), len(z_obs)
    if k == 0 or M == 0:
        return Matches.empty()
    r2 = np.broadcast_to(np.asarray(radius_px, dtype=float) ** 2, (k,))
    d2 = np.sum((z_pred[:, None, :] - z_obs[None, :, :]) ** 2, axis=2)  # (k, M)
    pi, fi = np.nonzero(d2 < r2[:, None])
    if not len(pi):
        return Matches.empty()
    dist = set_distances(desc_sets, n_desc, pi, desc_obs, fi)
    # per point: best and second-best distance among its gate's candidates (pi is sorted)
    order = np.lexsort((dist, pi))
    pi, fi, dist = pi[order], fi[order], dist[order]
    first = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    counts = np.diff(np.r_[first, len(pi)])
    second = np.where(counts > 1, dist[np.minimum(first + 1, len(dist) - 1)], np.inf)
    best = first[(dist[first] < max_distance) & (dist[first] < ratio * second)]
    bp, bf, bd = pi[best], fi[best], dist[best]
    # one point per feature: the smallest distance wins
    order = np.argsort(bd, kind="stable")
    _, keep = np.unique(bf[order], return_index=True)
    keep = np.sort(order[keep])
    return Matches(bp[keep], bf[keep], bd[keep], d2[bp[keep], bf[keep]])
