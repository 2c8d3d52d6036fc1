"""`cvslam refine`: one batch solution (a global bundle adjustment) over a fuse run.

A factor graph over every vehicle's keyframe poses and the landmarks they observed, solved
with GTSAM's sparse Levenberg-Marquardt (docs/refine.md):

- stereo reprojection factors, one per camera and observation (eq. 19: u_c = M^c [m; 1]),
  with the extract stage's pixel noise under a robust kernel (Huber or Cauchy);
- motion factors between consecutive keyframes of a vehicle: IMU preintegration with bias
  random walks for UAVs (`gtsam.CombinedImuFactor`), wheel-odometry relative poses for
  ground robots, a white-noise-acceleration (constant-velocity) prior with neither;
- the filter's own prior on each vehicle's first pose (the known initial pose, as the
  filter starts from): the gauge.

Cross-vehicle landmarks (one landmark variable observed by several vehicles) tie the
vehicles together as in the filter. Layers: `problem.py` (the arrays going in and out),
`keyframes.py`, `motion_factors.py`, `graph.py` (build, solve, marginals), `stage.py` (I/O).
"""
