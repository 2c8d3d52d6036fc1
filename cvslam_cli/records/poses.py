"""Pose tables: the trajectories stages exchange (estimates, dead reckoning, ground truth),
all in the nav frame (NED) by contract: TUM files, fuse outputs and the ground truth of logs
and of `cvslam eval --gt` files hold `T_nav_body`."""

from __future__ import annotations

from dataclasses import dataclass

from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses `T_nav_body`: `stamps_ns` (N,) increasing; `p_nav_m` (N, 3) body positions in
    the nav frame, metres; `q_nav_body_xyzw` (N, 4) unit quaternions (scalar last) of
    `C_nav_body`, rotating body coordinates into nav."""

    stamps_ns: I64
    p_nav_m: F64
    q_nav_body_xyzw: F64

    def __len__(self) -> int:
        return len(self.stamps_ns)
