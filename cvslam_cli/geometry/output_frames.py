"""The frames an estimate can be handed out in: the nav frame, a z-up ENU frame beside it,
and the dataset's own frame (the world and sensor its ground truth uses).

Inside, every pose is `T_nav_body` (NED nav frame, the vehicle's body frame; DESIGN.md
section 3). A tool that compares with a dataset's own ground truth (evo on KITTI's
`poses.txt`, on EuRoC's `data.csv`) needs the pose of the *same sensor* in the *same world*:

    T_world_sensor(t) = T_world_nav  T_nav_body(t)  T_body_sensor

with `T_world_nav` the inverse of the importer's `T_nav_world` (the dataset world -> nav
conversion applied once, at import) and `T_body_sensor` the sensor whose pose the dataset's
ground truth gives (KITTI: camera 0, optical frame; EuRoC: the IMU, i.e. the body itself).
The ENU frame is `T_enu_nav` (x east, y north, z up), the body frame unchanged: what a z-up
viewer shows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.geometry.nav_frames import R_NAV_WORLD
from cvslam_cli.geometry.rotations import (
    invert_T,
    is_rotation,
    make_T,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
)
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.poses import PoseTable

#: NED nav -> ENU (x east, y north, z up): the z-up display and export frame.
T_ENU_NAV: F64 = make_T(R_NAV_WORLD["enu"].T, np.zeros(3))


@dataclass(frozen=True, eq=False)
class DatasetFrame:
    """What "the dataset's frame" means for one imported log.

    `T_nav_world` (4, 4): dataset world -> nav (NED), the conversion the importer applied;
    `T_body_sensor` (4, 4): the sensor whose pose the dataset's ground truth gives, in the
    vehicle's body frame; `world`, `sensor`: their names in words (for file headers and
    messages). Both transforms must be rigid (a ValueError otherwise)."""

    T_nav_world: F64
    T_body_sensor: F64
    world: str
    sensor: str

    def __post_init__(self) -> None:
        for name in ("T_nav_world", "T_body_sensor"):
            T = np.asarray(getattr(self, name), dtype=np.float64)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f"{name}: expected a finite 4x4 matrix, got shape {T.shape}")
            if not (is_rotation(T[:3, :3], tol=1e-6) and np.allclose(T[3], [0, 0, 0, 1])):
                raise ValueError(f"{name}: not a rigid transform [R t; 0 0 0 1]")
            object.__setattr__(self, name, T)

    @property
    def T_world_nav(self) -> F64:
        return invert_T(self.T_nav_world)


def reexpress(table: PoseTable, T_world_nav: F64, T_body_sensor: F64) -> PoseTable:
    """`table` (poses `T_nav_body`) as poses `T_world_sensor = T_world_nav T_nav_body
    T_body_sensor`, same stamps. The quaternions are those of the composed rotations."""
    R_nb = quat_xyzw_to_matrix(np.asarray(table.q_nav_body_xyzw, dtype=np.float64))
    p_nb = np.asarray(table.p_nav_m, dtype=np.float64).reshape(-1, 3)
    R_wn, t_wn = T_world_nav[:3, :3], T_world_nav[:3, 3]
    R_bs, t_bs = T_body_sensor[:3, :3], T_body_sensor[:3, 3]
    R_ws = R_wn @ R_nb @ R_bs
    p_ws = (p_nb + R_nb @ t_bs) @ R_wn.T + t_wn
    q = matrix_to_quat_xyzw(R_ws) if len(table) else np.empty((0, 4))
    return PoseTable(np.asarray(table.stamps_ns, dtype=np.int64), p_ws, q.reshape(-1, 4))
