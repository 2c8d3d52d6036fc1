"""Landmark mode: point landmarks and their per-frame stereo observations, written in the
feature format of `cvslam extract` (docs/feature_format.md) so the filter can be run many
times (Monte Carlo) without rendering or feature extraction.

Each landmark has a fixed SIFT-like descriptor (unit-norm, non-negative, scaled to 512 and
clipped to a byte, as OpenCV's SIFT stores them). A frame observes the landmarks in front of
both cameras, inside both images, within range and not hidden by a wall; each camera misses
each landmark independently with `miss_probability`. Observed pixels get independent
Gaussian noise; descriptors a per-observation perturbation. Landmarks seen in both images
are matched (true id); `outlier_fraction` of the matches of a frame are wrong matches
(random pixels with a disparity inside the search window and a random SIFT-like descriptor,
id -2), and `lookalike_fraction` are look-alikes of a landmark in view (repeated texture:
its descriptor perturbed as a true observation's, its disparity, at a pixel up to
`lookalike_offset_px` from its own in both images, id -2): the wrong matches that can pass
the filter's innovation gate and descriptor test, where random ones never do. With
`observer_offset_m` each vehicle observes the landmarks displaced by offsets of its own
(`seen_by`): one point, different keypoints from different viewpoints. Matches are
triangulated with the same inverse observation model as extract.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.camera import CameraModel, StereoRig
from cvslam_cli.geometry.projection import distort_normalized, project_points
from cvslam_cli.geometry.rotations import invert_T
from cvslam_cli.geometry.stereo import (
    projection_matrices,
    triangulate,
    triangulation_covariance,
)
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.features import DESCRIPTOR_SIZE
from cvslam_cli.sim.scenario import LandmarkMode


@dataclass(frozen=True, eq=False)
class LandmarkWorld:
    """p_nav_m (L, 3) true positions; descriptor (L, 128) uint8; occluders: (W, 2, 2) wall
    segments (north, east) with heights (W,) (walls stand on z = 0 up to z = -height),
    empty for open terrain."""

    p_nav_m: F64
    descriptor: NDArray[np.uint8]
    wall_segments_ne: F64
    wall_heights_m: F64


def seen_by(world: LandmarkWorld, offset_sigma_m: float, rng: np.random.Generator) -> LandmarkWorld:
    """The landmarks as one vehicle observes them: each displaced by its own Gaussian offset
    (standard deviation `offset_sigma_m` per nav axis), drawn once from `rng` (the vehicle's
    stream) and kept for every frame. `world` itself when the deviation is 0 (no draw)."""
    if offset_sigma_m <= 0.0:
        return world
    offset = rng.normal(0.0, offset_sigma_m, world.p_nav_m.shape)
    return replace(world, p_nav_m=world.p_nav_m + offset)


def sift_like_descriptors(n: int, rng: np.random.Generator) -> NDArray[np.uint8]:
    raw = np.abs(rng.standard_normal((n, DESCRIPTOR_SIZE))) ** 2
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    return np.clip(np.rint(raw * 512.0), 0, 255).astype(np.uint8)


def make_world(
    points_nav_m: F64, rng: np.random.Generator, walls: tuple[F64, F64] | None = None
) -> LandmarkWorld:
    segs, heights = walls if walls is not None else (np.zeros((0, 2, 2)), np.zeros(0))
    return LandmarkWorld(
        np.asarray(points_nav_m, dtype=float),
        sift_like_descriptors(len(points_nav_m), rng),
        segs,
        heights,
    )


def occluded(c_nav_m: F64, p_nav_m: F64, segs: F64, heights: F64) -> NDArray[np.bool_]:
    """(N,) True where the segment camera -> point crosses a wall before reaching the point."""
    if segs.shape[0] == 0 or p_nav_m.shape[0] == 0:
        return np.zeros(p_nav_m.shape[0], dtype=bool)
    c = c_nav_m[:2]
    d = p_nav_m[:, :2] - c  # (N, 2)
    a, b = segs[:, 0], segs[:, 1]  # (W, 2)
    e = b - a
    denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (N, W)
    ac = a[None, :, :] - c[None, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ac[..., 0] * e[None, :, 1] - ac[..., 1] * e[None, :, 0]) / denom
        s = (ac[..., 0] * d[:, None, 1] - ac[..., 1] * d[:, None, 0]) / denom
    z_at = c_nav_m[2] + t * (p_nav_m[:, None, 2] - c_nav_m[2])
    hit = (
        (np.abs(denom) > 1e-12)
        & (t > 1e-6)
        & (t < 1.0 - 1e-6)
        & (s >= 0)
        & (s <= 1)
        & (z_at <= 0.0)
        & (z_at >= -heights[None, :])
    )
    return hit.any(axis=1)


def _pixels(cam: CameraModel, p_cam: F64) -> tuple[F64, F64]:
    """Ideal (undistorted) pixels and raw (distorted) pixels of camera-frame points."""
    xy = p_cam[:, :2] / p_cam[:, 2:3]
    ideal = xy @ cam.K[:2, :2].T + cam.K[:2, 2]
    raw, _ = project_points(cam, p_cam)
    return ideal, raw


def _raw_from_ideal(cam: CameraModel, uv: F64) -> F64:
    xy = (uv - cam.K[:2, 2]) @ np.linalg.inv(cam.K[:2, :2]).T
    return distort_normalized(cam, xy) @ cam.K[:2, :2].T + cam.K[:2, 2]


def _inside(cam: CameraModel, uv: F64) -> NDArray[np.bool_]:
    return (
        (uv[:, 0] >= 0)
        & (uv[:, 0] <= cam.width - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= cam.height - 1)
    )


def _keypoints(
    uv_px: F64, uv_raw: F64, desc: NDArray[np.uint8], rng: np.random.Generator
) -> dict[str, np.ndarray]:
    n = uv_px.shape[0]
    size_px = rng.uniform(2.0, 8.0, n)
    angle_deg = rng.uniform(0.0, 360.0, n)
    response = rng.uniform(0.01, 0.1, n)
    rng.integers(0, 4, n)  # octaves were drawn here: a seed keeps the scenes it gave
    return {
        "uv_raw_px": uv_raw,
        "uv_px": uv_px,
        "size_px": size_px,
        "angle_deg": angle_deg,
        "response": response,
        # every keypoint at octave 0: the noise added is one sigma whatever the keypoint
        # (estimation/octave_noise.py reads the octave as the scale of its bearing noise)
        "octave": np.zeros(n, np.int32),
        "desc": desc,
    }


def _lookalikes(
    rig: StereoRig,
    ideal_l: F64,
    ideal_r: F64,
    n_true: int,
    mode: LandmarkMode,
    rng: np.random.Generator,
) -> tuple[F64, F64, NDArray[np.int64]]:
    """Look-alike wrong matches of a frame whose landmarks in view project to ideal_l,
    ideal_r (n, 2): about `lookalike_fraction` of the frame's matches (n_true true ones), each
    imitating a landmark drawn from those in view (seen or missed), at its pixels moved by one
    offset uniform in a disc of radius `lookalike_offset_px` (the same disparity) plus pixel
    noise, kept where inside both images. Returns left (k, 2), right (k, 2) ideal pixels and
    the imitated landmarks' rows (k,). No random draw when the fraction is 0 (scenarios
    without look-alikes simulate as before, bit for bit)."""
    f = mode.lookalike_fraction
    none = np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    if f <= 0 or not n_true or not len(ideal_l):
        return none
    k = int(rng.binomial(n_true, f / (1.0 - f)))
    if not k:
        return none
    src = rng.integers(0, len(ideal_l), k)
    angle = rng.uniform(0.0, 2.0 * np.pi, k)
    radius = mode.lookalike_offset_px * np.sqrt(rng.uniform(0.0, 1.0, k))
    offset = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    sigma = mode.pixel_noise_px
    look_l = ideal_l[src] + offset + rng.normal(0.0, sigma, (k, 2))
    look_r = ideal_r[src] + offset + rng.normal(0.0, sigma, (k, 2))
    keep = _inside(rig.left, look_l) & _inside(rig.right, look_r)
    return look_l[keep], look_r[keep], src[keep].astype(np.int64)


def observe_frame(
    world: LandmarkWorld,
    rig: StereoRig,
    T_nav_left: F64,
    mode: LandmarkMode,
    rng: np.random.Generator,
) -> tuple[dict, dict, dict]:
    """One stereo frame: (left keypoints, right keypoints, matches) for
    `FeatureSetBuilder.add_frame` (frame-local match indices)."""
    T_left_nav = invert_T(T_nav_left)
    T_right_nav = invert_T(rig.T_left_right) @ T_left_nav
    p_l = world.p_nav_m @ T_left_nav[:3, :3].T + T_left_nav[:3, 3]
    p_r = world.p_nav_m @ T_right_nav[:3, :3].T + T_right_nav[:3, 3]
    cand = (p_l[:, 2] > 0.1) & (p_r[:, 2] > 0.1) & (np.linalg.norm(p_l, axis=1) < mode.max_range_m)
    idx = np.flatnonzero(cand)
    ideal_l, raw_l = _pixels(rig.left, p_l[idx])
    ideal_r, raw_r = _pixels(rig.right, p_r[idx])
    keep = _inside(rig.left, raw_l) & _inside(rig.right, raw_r)
    idx, ideal_l, ideal_r = idx[keep], ideal_l[keep], ideal_r[keep]
    if world.wall_segments_ne.shape[0]:
        vis = ~occluded(
            T_nav_left[:3, 3], world.p_nav_m[idx], world.wall_segments_ne, world.wall_heights_m
        )
        idx, ideal_l, ideal_r = idx[vis], ideal_l[vis], ideal_r[vis]
    n = idx.size
    seen_l = rng.random(n) >= mode.miss_probability
    seen_r = rng.random(n) >= mode.miss_probability
    sigma = mode.pixel_noise_px
    uv_l = ideal_l + rng.normal(0.0, sigma, (n, 2))
    uv_r = ideal_r + rng.normal(0.0, sigma, (n, 2))

    def perturb(desc: NDArray[np.uint8]) -> NDArray[np.uint8]:
        noisy = desc.astype(float) + rng.normal(0.0, mode.descriptor_noise, desc.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    desc_l = perturb(world.descriptor[idx])
    desc_r = perturb(world.descriptor[idx])
    both = seen_l & seen_r
    # wrong matches: random left pixel, right pixel at a plausible disparity, look-alike desc
    n_true = int(both.sum())
    f = mode.outlier_fraction
    n_out = int(rng.binomial(n_true, f / (1.0 - f))) if 0 < f < 1 and n_true else 0
    M_l, M_r = projection_matrices(rig)
    out_l = np.column_stack(
        [rng.uniform(0, rig.left.width - 1, n_out), rng.uniform(0, rig.left.height - 1, n_out)]
    )
    median_disp = float(np.median(ideal_l[:, 0] - ideal_r[:, 0])) if n else 10.0
    out_r = out_l - np.column_stack(
        [rng.uniform(0.2, 2.0, n_out) * max(median_disp, 1.0), rng.normal(0.0, 1.0, n_out)]
    )
    out_desc_l = sift_like_descriptors(n_out, rng)
    out_desc_r = perturb(out_desc_l)

    look_l, look_r, look_src = _lookalikes(rig, ideal_l, ideal_r, n_true, mode, rng)
    if len(look_src):
        out_l, out_r = np.vstack([out_l, look_l]), np.vstack([out_r, look_r])
        out_desc_l = np.vstack([out_desc_l, perturb(world.descriptor[idx[look_src]])])
        out_desc_r = np.vstack([out_desc_r, perturb(world.descriptor[idx[look_src]])])
        n_out += len(look_src)

    left_uv = np.vstack([uv_l[seen_l], out_l])
    right_uv = np.vstack([uv_r[seen_r], out_r])
    left_desc = np.vstack([desc_l[seen_l], out_desc_l])
    right_desc = np.vstack([desc_r[seen_r], out_desc_r])
    # frame-local indices of the true matches, then the outliers and look-alikes
    pos_l = np.cumsum(seen_l) - 1
    pos_r = np.cumsum(seen_r) - 1
    m_left = np.concatenate([pos_l[both], int(seen_l.sum()) + np.arange(n_out)])
    m_right = np.concatenate([pos_r[both], int(seen_r.sum()) + np.arange(n_out)])
    ids = np.concatenate([idx[both], np.full(n_out, -2)]).astype(np.int64)

    uvl_m, uvr_m = left_uv[m_left], right_uv[m_right]
    p_cam = triangulate(M_l, M_r, uvl_m, uvr_m) if m_left.size else np.zeros((0, 3))
    good = (p_cam[:, 2] > 0.1) & (np.linalg.norm(p_cam, axis=1) < mode.max_range_m)
    m_left, m_right, ids, p_cam = m_left[good], m_right[good], ids[good], p_cam[good]
    uvl_m, uvr_m = uvl_m[good], uvr_m[good]
    cov = triangulation_covariance(M_l, M_r, uvl_m, uvr_m, max(sigma, 0.05), p_cam)
    dl, dr = left_desc[m_left].astype(float), right_desc.astype(float)
    # squared distances |a|^2 + |b|^2 - 2 a.b for every (match, right keypoint) pair
    sq = (dl * dl).sum(1)[:, None] + (dr * dr).sum(1)[None, :] - 2.0 * dl @ dr.T
    dist_all = np.sqrt(np.maximum(sq, 0.0))
    rows = np.arange(m_left.size)
    d1 = dist_all[rows, m_right]
    dist_all[rows, m_right] = np.inf
    d2 = dist_all.min(axis=1) if dist_all.shape[1] > 1 else np.full(m_left.size, np.inf)
    left = _keypoints(left_uv, _raw_from_ideal(rig.left, left_uv), left_desc, rng)
    right = _keypoints(right_uv, _raw_from_ideal(rig.right, right_uv), right_desc, rng)
    matches = {
        "left": m_left,
        "right": m_right,
        "disparity_px": uvl_m[:, 0] - uvr_m[:, 0],
        "distance": d1,
        "ratio": np.where(np.isfinite(d2), d1 / np.maximum(d2, 1e-9), 0),
        "p_cam_m": p_cam,
        "cov_cam_m2": cov,
        "landmark_id": ids,
    }
    return left, right, matches
