"""When one linearised update is not enough: a vehicle whose pose has become too uncertain
for the linearisation of the observation model (extension beyond the paper).

After a long gap in the images (a camera blackout, a stretch without texture) a vehicle is
dead-reckoned for seconds and its position uncertainty grows to metres. When it sees mapped
ground again the filter's windows still find the landmarks (their chi-square gates grow with
the uncertainty: found at 11 m of position standard deviation from 60 m up, BENCHMARKS.md
"Fuse: large corrections"), but one update linearised at the dead-reckoned pose cannot make
the correction: metres at a range of tens of metres are bearing errors of a tenth of a
radian, and the update leaves metres of error under a covariance that claims decimetres.
Such a frame's update is iterated instead (`update.VisualUpdater.iterated_update`, the
iterated EKF: relinearised at its own estimate until it settles).

Too uncertain: the vehicle's position standard deviation along its least known direction
exceeds `ratio` times the median depth of the frame's stereo points, the bearing error (rad)
its linearisation would carry (`too_uncertain`). Or, per observation, a landmark placed in
the image no better than a bearing standard deviation `limit_rad` (`bearings_too_uncertain`):
the vehicle's uncertainty and the landmark's own, projected. A far point one vehicle mapped
is metres long along its ray; another vehicle that sees it from the side finds it tens of
pixels from where it is predicted, and one update linearised at the prediction leaves it
far off under a covariance that claims centimetres (BENCHMARKS.md "Fuse: a far landmark
seen from the side").
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.records.arrays import F64


def too_uncertain(cov_p_nav_m2: F64, p_cam_m: F64, ratio: float) -> bool:
    """Whether a vehicle with position covariance cov_p_nav_m2 (3, 3) is too uncertain for
    one linearised update with a frame whose stereo points are p_cam_m (M, 3) (left camera
    frame): module docstring. ratio <= 0: never."""
    if ratio <= 0 or not len(p_cam_m):
        return False
    depth = p_cam_m[:, 2]
    depth = depth[np.isfinite(depth) & (depth > 0)]
    if not len(depth):
        return False
    sigma_m = float(np.sqrt(np.linalg.eigvalsh(cov_p_nav_m2)[-1]))
    return sigma_m > ratio * float(np.median(depth))


def bearings_too_uncertain(
    S_left_px2: F64, R_left_px2: F64, fx_px: float, limit_rad: float
) -> bool:
    """Whether some observation's prediction is too uncertain for one linearised update:
    S_left_px2 (k, 2, 2) the left-image blocks of their innovation covariances, R_left_px2
    (2, 2) or (k, 2, 2) the pixel noise's share in them. The largest standard deviation of
    S - R (the vehicle's and the landmark's uncertainty, projected) over fx_px is the bearing
    error (rad) a linearisation at the prediction carries (module docstring). limit_rad <= 0:
    never."""
    if limit_rad <= 0 or not len(S_left_px2):
        return False
    spread = np.linalg.eigvalsh(np.asarray(S_left_px2) - np.asarray(R_left_px2))[:, -1]
    return bool(np.sqrt(max(float(spread.max()), 0.0)) > limit_rad * fx_px)
