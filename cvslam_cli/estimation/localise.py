"""Localising a vehicle in the shared map from one stereo frame (extension beyond the paper:
a vehicle whose initial pose is unknown, only a rough prior).

The paper starts every vehicle from a known pose. A vehicle that starts from a rough prior
(metres of position, tens of degrees of heading) cannot use the filter's innovation windows:
they are as wide as the image and the linearisation is poor. Instead, each of its frames is
matched to the landmarks in the state by descriptor alone (nearest neighbour, ratio test, one
match per landmark), and the left-image pixels of those putative pairs give the left camera's
pose by PnP inside RANSAC (OpenCV). The pose is refined on the inliers (Levenberg-Marquardt),
and an inlier must also reproject within the threshold in the right image (the stereo
constraint). With at least `min_inliers` the camera pose is turned into the body pose:

    p_c = R_cam_body (C^T (m - p) - t_body_cam) = R m + t  (eq. 19's camera model)
    =>  C_nav_body = R^T R_cam_body,   p = -R^T (t + R_cam_body t_body_cam)

The filter then relinearises the vehicle at this pose and updates with the inlier landmarks
(`slam.py`), so the vehicle's correlation with the map is built as for any observation.
Pure numpy/OpenCV; RANSAC is seeded, so a run is reproducible.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.association import descriptor_distances
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.geometry.rotations import matrix_to_euler_zyx
from cvslam_cli.records.arrays import F64, I64

RANSAC_ITERATIONS = 300
RANSAC_CONFIDENCE = 0.999


@dataclass(frozen=True, eq=False)
class Localisation:
    """The body pose p_nav_m (3,), euler_rad (3,) found from k inliers: `landmark_rows` (k,)
    rows of the map given, `match_rows` (k,) rows of the frame's matches, `rms_px` their
    reprojection RMS over both images, `candidates` the putative descriptor pairs tried."""

    p_nav_m: F64
    euler_rad: F64
    landmark_rows: I64
    match_rows: I64
    rms_px: float
    candidates: int


def descriptor_pairs(
    desc_obs: NDArray[np.uint8],
    desc_map: NDArray[np.uint8],
    ratio: float,
    max_distance: float,
) -> tuple[I64, I64]:
    """Putative pairs (match rows, map rows): each match's nearest map descriptor if it passes
    the ratio test against the second nearest and `max_distance`; a map row claimed by several
    matches keeps the closest."""
    if len(desc_obs) == 0 or len(desc_map) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    D = descriptor_distances(desc_obs, desc_map)  # (M, N)
    two = np.argpartition(D, 1, axis=1)[:, :2]
    d2 = np.take_along_axis(D, two, axis=1)
    first = np.argmin(d2, axis=1)
    best = two[np.arange(len(D)), first]
    d1 = d2[np.arange(len(D)), first]
    second = d2[np.arange(len(D)), 1 - first]
    ok = np.flatnonzero((d1 < ratio * second) & (d1 < max_distance))
    # one match per map row: the smallest distance wins
    order = ok[np.lexsort((d1[ok], best[ok]))]
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = best[order][1:] != best[order][:-1]
    rows = order[keep]
    return rows.astype(np.int64), best[rows].astype(np.int64)


def body_pose_from_camera(
    obs: StereoObservationModel, R_cam_nav: F64, t_cam: F64
) -> tuple[F64, F64]:
    """(p_nav_m, euler_rad) of the body whose left camera maps nav points m to R m + t."""
    R_cb = obs.R_cam_body[0]
    C = R_cam_nav.T @ R_cb
    p = -R_cam_nav.T @ (t_cam + R_cb @ obs.t_body_cam[0])
    return p, matrix_to_euler_zyx(C)


def localise(
    obs: StereoObservationModel,
    z_obs: F64,
    desc_obs: NDArray[np.uint8],
    m_nav_m: F64,
    desc_map: NDArray[np.uint8],
    *,
    ratio: float,
    max_descriptor_distance: float,
    reprojection_px: float,
    min_inliers: int,
    seed: int = 0,
) -> Localisation | None:
    """The body pose from a frame's stereo matches z_obs (M, 4) (u_l, v_l, u_r, v_r ideal
    pixels) with descriptors (M, 128) against map landmarks m_nav_m (N, 3) with descriptors
    (N, 128); None when fewer than `min_inliers` agree (module docstring)."""
    rows, lm = descriptor_pairs(desc_obs, desc_map, ratio, max_descriptor_distance)
    if len(rows) < max(min_inliers, 4):
        return None
    cv2.setRNGSeed(seed)
    obj = np.ascontiguousarray(m_nav_m[lm], dtype=np.float64)
    img = np.ascontiguousarray(z_obs[rows, :2], dtype=np.float64)
    K = np.asarray(obs.K[0], dtype=np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj,
        img,
        K,
        None,
        iterationsCount=RANSAC_ITERATIONS,
        reprojectionError=float(reprojection_px),
        confidence=RANSAC_CONFIDENCE,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    R_cam_nav, _ = cv2.Rodrigues(rvec)
    p, euler = body_pose_from_camera(obs, R_cam_nav, tvec.ravel())
    # every putative pair, re-checked at the refined pose in both images
    z_pred, _, _ = obs.predict(p, euler, obj)
    res = (z_pred - z_obs[rows]).reshape(-1, 2, 2)
    dist = np.linalg.norm(res, axis=2)  # (k, 2): left and right image
    with np.errstate(invalid="ignore"):
        good = np.flatnonzero(np.all(dist < reprojection_px, axis=1))
    if len(good) < min_inliers:
        return None
    rms = float(np.sqrt(np.mean(res[good] ** 2)))
    return Localisation(p, euler, lm[good], rows[good], rms, len(rows))
