"""Pinhole projection with lens distortion, and the inverse (pixel rays), vectorised.

Pixel coordinates follow OpenCV: (u, v) = (column, row) with integer values at pixel
centres. Distortion models: `plumb_bob` (k1, k2, p1, p2[, k3]), `equidistant` (fisheye
k1..k4), `none`. The forward model is written out in numpy (exact, fast for many points);
the inverse uses OpenCV's iterative undistortion to a tolerance far below a pixel.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.records.arrays import F64


def _coeffs(cam: CameraModel, n: int) -> F64:
    d = np.zeros(n)
    k = np.asarray(cam.D, dtype=float)[:n]
    d[: k.size] = k
    return d


def distort_normalized(cam: CameraModel, xy: F64) -> F64:
    """(N, 2) ideal normalised coordinates (x/z, y/z) -> distorted normalised coordinates."""
    xy = np.asarray(xy, dtype=float)
    if not cam.has_distortion or cam.distortion_model == "none":
        return xy.copy()
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    if cam.distortion_model == "equidistant":
        k1, k2, k3, k4 = _coeffs(cam, 4)
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        return xy * scale[:, None]
    if cam.distortion_model == "rational_polynomial":
        k1, k2, p1, p2, k3, k4, k5, k6 = _coeffs(cam, 8)
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    else:  # plumb_bob
        k1, k2, p1, p2, k3 = _coeffs(cam, 5)
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def project_points(cam: CameraModel, p_cam: F64) -> tuple[F64, NDArray[np.bool_]]:
    """(N, 3) points in the camera optical frame -> (N, 2) raw pixel coordinates and a
    mask of points in front of the camera (z > 0). Pixels of points behind are NaN."""
    p = np.asarray(p_cam, dtype=float).reshape(-1, 3)
    front = p[:, 2] > 1e-9
    z = np.where(front, p[:, 2], np.nan)
    xy = distort_normalized(cam, p[:, :2] / z[:, None])
    K = cam.K
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1), front


def undistort_pixels(cam: CameraModel, uv: F64) -> F64:
    """(N, 2) raw pixel coordinates -> (N, 2) ideal normalised coordinates (x/z, y/z)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 1, 2)
    if not cam.has_distortion or cam.distortion_model == "none":
        Kinv = np.linalg.inv(cam.K)
        h = np.concatenate([uv[:, 0, :], np.ones((uv.shape[0], 1))], axis=1) @ Kinv.T
        return h[:, :2] / h[:, 2:3]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if cam.distortion_model == "equidistant":
        out = cv2.fisheye.undistortPoints(uv, cam.K, _coeffs(cam, 4), criteria=criteria)
    else:
        D = np.asarray(cam.D, dtype=float)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
            out = cv2.undistortPointsIter(uv, cam.K, D, None, None, criteria)
        else:  # OpenCV 5: undistortPoints takes the criteria
            out = cv2.undistortPoints(uv, cam.K, D, criteria=criteria)
    return out.reshape(-1, 2).astype(float)


def pixel_rays(cam: CameraModel) -> F64:
    """(H, W, 3) ray directions (x/z, y/z, 1) in the camera optical frame through the centre
    of every pixel of the raw (distorted) image."""
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(float)
    xy = undistort_pixels(cam, np.stack([u.ravel(), v.ravel()], axis=1))
    rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    return rays.reshape(cam.height, cam.width, 3)
