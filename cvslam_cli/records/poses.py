"""Pose tables: the trajectories stages exchange (estimates, dead reckoning, ground truth)."""

from __future__ import annotations

from dataclasses import dataclass

from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses `T_frame_body`: `stamps_ns` (N,) increasing, `p_m` (N, 3), `q_xyzw` (N, 4)
    rotating body coordinates into the table's frame."""

    stamps_ns: I64
    p_m: F64
    q_xyzw: F64

    def __len__(self) -> int:
        return len(self.stamps_ns)
