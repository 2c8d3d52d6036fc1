"""World frames ground truth comes in, and the rotation of each into the nav frame (NED).

A ground-truth source states its world frame once (`logs.vehicles.<name>.ground_truth_frame`)
and is converted once, where it is read: p_nav = R_nav_world p_world, C_nav_body =
R_nav_world C_world_body. Only the world frame changes: the body frame stays the one the
truth was recorded for (the vehicle's body frame, that of its IMU and rig).

- `ned`: x north, y east, z down (DESIGN.md section 3; cvslam's own logs);
- `enu`: x east, y north, z up (ROS REP 103 `map`/`odom`, motion capture with z up);
- `nwu`: x north, y west, z up (the other common z-up convention);
- `camera`: a camera optical frame taken as the world, x right, y down, z forward (KITTI's
  poses, visual odometry output): forward -> north, right -> east, down -> down.
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.poses import PoseTable

R_NAV_WORLD: dict[str, F64] = {
    "ned": np.eye(3),
    "enu": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
    "nwu": np.diag([1.0, -1.0, -1.0]),
    "camera": np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
}
GROUND_TRUTH_FRAMES = tuple(R_NAV_WORLD)


def pose_to_nav(p_world_m: F64, q_world_body_xyzw: F64, frame: str) -> tuple[F64, F64]:
    """(p_nav_m (..., 3), q_nav_body_xyzw (..., 4)) of poses in world `frame`; a quaternion
    of NaNs (position-only truth) stays NaN."""
    R = R_NAV_WORLD[frame]
    p = np.asarray(p_world_m, dtype=float) @ R.T
    q = np.asarray(q_world_body_xyzw, dtype=float)
    if frame == "ned" or not np.all(np.isfinite(q)):
        return p, q.copy()
    return p, matrix_to_quat_xyzw(R @ quat_xyzw_to_matrix(q))


def table_to_nav(table: PoseTable, frame: str) -> PoseTable:
    """`table` (poses in world `frame`) in the nav frame."""
    p, q = pose_to_nav(table.p_nav_m, table.q_nav_body_xyzw, frame)
    return PoseTable(table.stamps_ns, p, q)
