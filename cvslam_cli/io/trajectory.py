"""Trajectory tables and files.

TUM format (what evo reads): one pose per line, `t x y z qx qy qz qw`, t in seconds; cvslam
writes t exactly from integer nanoseconds (9 decimals, no float rounding) and the pose of
the body in the nav frame (NED).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class PoseTable:
    """Poses `T_frame_body`: `stamps_ns` (N,) increasing, `p_m` (N, 3), `q_xyzw` (N, 4)
    rotating body coordinates into the table's frame."""

    stamps_ns: I64
    p_m: F64
    q_xyzw: F64

    def __len__(self) -> int:
        return len(self.stamps_ns)


def ns_to_seconds_text(stamp_ns: int) -> str:
    """Exact decimal seconds of an integer nanosecond stamp ("1403715273.262142976")."""
    sign = "-" if stamp_ns < 0 else ""
    sec, ns = divmod(abs(int(stamp_ns)), 1_000_000_000)
    return f"{sign}{sec}.{ns:09d}"


def write_tum(path: Path, table: PoseTable, *, header: str = "") -> None:
    """Write `table` as a TUM file (temporary name, renamed when complete)."""
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    lines.append("# timestamp_s x y z qx qy qz qw")
    for t, p, q in zip(table.stamps_ns, table.p_m, table.q_xyzw, strict=True):
        lines.append(ns_to_seconds_text(int(t)) + " " + " ".join(f"{v:.9f}" for v in (*p, *q)))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    os.replace(tmp, path)
