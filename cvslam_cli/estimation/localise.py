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
CONFIRM_RANGE_FRACTION = 0.05
"""Two localisations of consecutive frames agree when the offsets of their poses from the
filter's differ by less than this fraction of the median range from the camera to the
inlier landmarks (m / m) ..."""
CONFIRM_YAW_RAD = float(np.radians(3.0))
"""... and their heading offsets by less than this (rad)."""


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


@dataclass(frozen=True)
class _Pending:
    """A localisation waiting for confirmation: the offset of the pose found from the
    filter's (position (3,), heading) and in how many consecutive frames it held."""

    dp_m: F64
    dyaw_rad: float
    frames: int


class PoseConfirmation:
    """Against a chance fit to look-alikes: a pose found by PnP counts once the same pose is
    found in `frames` consecutive frames of the vehicle. The same pose: the offset from the
    filter's pose repeats (the filter's dead reckoning moves by centimetres between frames,
    a PnP pose on a map known to metres scatters by a few per cent of the range; a chance
    fit does not land on the same offset twice)."""

    def __init__(self, frames: int) -> None:
        self.frames = frames
        self._pending: dict[str, _Pending] = {}

    @staticmethod
    def tolerance_m(ranges_m: F64) -> float:
        """The position tolerance of a localisation whose inliers lie at `ranges_m` (k,)."""
        return CONFIRM_RANGE_FRACTION * float(np.median(ranges_m))

    def confirmed(self, name: str, dp_m: F64, dyaw_rad: float, tol_m: float) -> bool:
        """Whether vehicle `name`'s offset in this frame, with those of the frames before,
        makes `frames` consecutive agreeing frames."""
        last = self._pending.get(name)
        agrees = (
            last is not None
            and float(np.linalg.norm(dp_m - last.dp_m)) < tol_m
            and abs(dyaw_rad - last.dyaw_rad) < CONFIRM_YAW_RAD
        )
        frames = last.frames + 1 if agrees and last is not None else 1
        self._pending[name] = _Pending(dp_m, dyaw_rad, frames)
        return frames >= self.frames

    def waiting(self, name: str) -> bool:
        """Whether a pose of vehicle `name` waits for more frames."""
        return name in self._pending

    def drop(self, name: str) -> None:
        """Forget vehicle `name`'s pending pose (a frame found none, or it was accepted)."""
        self._pending.pop(name, None)


def descriptor_pairs(
    desc_obs: NDArray[np.uint8],
    desc_map: NDArray[np.uint8],
    ratio: float,
    max_distance: float,
    age: I64 | None = None,
) -> tuple[I64, I64]:
    """Putative pairs (match rows, map rows): each match's nearest map descriptor if it passes
    the ratio test against the second nearest and `max_distance`; a map row claimed by several
    matches keeps the closest.

    With `age` (N,) (the order the map rows were mapped in, e.g. book ids): a point mapped
    twice -- evicted and mapped again, or mapped anew from a pose gone wrong (a lost
    vehicle's) -- has two map rows whose descriptors are as close to each other as to the
    match. The ratio test of the two would reject both; instead, when the two nearest are
    such duplicates (both, and their distance to each other, pass the ratio test against
    the third nearest), the match is tested against the third and paired with the older."""
    if len(desc_obs) == 0 or len(desc_map) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    D = descriptor_distances(desc_obs, desc_map)  # (M, N)
    k = 3 if age is not None and D.shape[1] >= 3 else 2
    near = np.argpartition(D, k - 1, axis=1)[:, :k]
    dk = np.take_along_axis(D, near, axis=1)
    order = np.argsort(dk, axis=1, kind="stable")
    near = np.take_along_axis(near, order, axis=1)
    dk = np.take_along_axis(dk, order, axis=1)
    best, d1, second = near[:, 0], dk[:, 0], dk[:, 1]
    if k == 3:
        assert age is not None
        mutual = np.linalg.norm(
            desc_map[near[:, 0]].astype(np.float32) - desc_map[near[:, 1]], axis=1
        )
        dup = (dk[:, 1] < ratio * dk[:, 2]) & (mutual < ratio * dk[:, 2])
        older = dup & (age[near[:, 1]] < age[near[:, 0]])
        best = np.where(older, near[:, 1], best)
        d1 = np.where(older, dk[:, 1], d1)
        second = np.where(dup, dk[:, 2], second)
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
    age: I64 | None = None,
) -> Localisation | None:
    """The body pose from a frame's stereo matches z_obs (M, 4) (u_l, v_l, u_r, v_r ideal
    pixels) with descriptors (M, 128) against map landmarks m_nav_m (N, 3) with descriptors
    (N, 128); None when fewer than `min_inliers` agree (module docstring). `age` (N,): the
    order the landmarks were mapped in, to pair a point mapped twice with its older
    mapping (`descriptor_pairs`)."""
    rows, lm = descriptor_pairs(desc_obs, desc_map, ratio, max_descriptor_distance, age)
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
    z_pred = obs.project(p, euler, obj)
    res = (z_pred - z_obs[rows]).reshape(-1, 2, 2)
    dist = np.linalg.norm(res, axis=2)  # (k, 2): left and right image
    with np.errstate(invalid="ignore"):
        good = np.flatnonzero(np.all(dist < reprojection_px, axis=1))
    if len(good) < min_inliers:
        return None
    rms = float(np.sqrt(np.mean(res[good] ** 2)))
    return Localisation(p, euler, lm[good], rows[good], rms, len(rows))
