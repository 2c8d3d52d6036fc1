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
its linearisation would carry.
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
