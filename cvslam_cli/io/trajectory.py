"""Trajectory tables and files.

TUM format (what evo reads): one pose per line, `t x y z qx qy qz qw`, t in seconds; cvslam
writes t exactly from integer nanoseconds (9 decimals, no float rounding) and the pose of
the body in the nav frame (NED). `read_tum` parses t back to integer nanoseconds from the
decimal text (never through a float), so `read_tum(write_tum(table))` has the same stamps and
the values to the 9 written decimals.

KITTI pose format (what evo reads with `evo_traj kitti`): one pose per line, the 12 numbers
of the row-major 3x4 matrix [R | t] of `T_world_body`, no stamps and no comments.

EuRoC ground-truth CSV (`state_groundtruth_estimate0/data.csv`): `timestamp [ns], p x y z,
q w x y z, ...` (velocity and biases follow; ignored), comma-separated, '#' header.
`read_trajectory_file` tells the three apart by their lines.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.rotations import (
    matrix_to_quat_xyzw,
    nearest_rotation,
    quat_xyzw_to_matrix,
)
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.io.textfiles import (
    check_stamps_increasing,
    data_lines,
    finite_floats,
    ns_to_seconds_text,
    read_text,
    seconds_text_to_ns,
)
from cvslam_cli.records.arrays import F64, I64, check_shape
from cvslam_cli.records.poses import PoseTable


def write_tum(path: Path, table: PoseTable, *, header: str = "") -> None:
    """Write `table` as a TUM file (temporary name, renamed when complete)."""
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    lines.append("# timestamp_s x y z qx qy qz qw")
    for t, p, q in zip(table.stamps_ns, table.p_nav_m, table.q_nav_body_xyzw, strict=True):
        lines.append(ns_to_seconds_text(int(t)) + " " + " ".join(f"{v:.9f}" for v in (*p, *q)))
    write_text_atomic(path, "\n".join(lines) + "\n")


# -- reading TUM, KITTI --------------------------------------------------------------------

_QUAT_NORM_TOL = 1e-2
_ROTATION_TOL = 1e-2


def first_non_unit(norms: F64, tol: float = _QUAT_NORM_TOL) -> int | None:
    """Index of the first quaternion norm further than `tol` from 1, or None."""
    bad = np.flatnonzero(np.abs(norms - 1.0) > tol)
    return int(bad[0]) if bad.size else None


def read_tum(path: Path, error: type[CvslamError] = CvslamError) -> PoseTable:
    """Read a TUM file (`t x y z qx qy qz qw` per line, whitespace or commas, '#' comments):
    the inverse of `write_tum`. Stamps are parsed exactly from the decimal text (rounded
    half to even to ns beyond 9 decimals); values are kept as written (no renormalisation).
    `error` naming the file and line for a malformed line, a quaternion whose norm is
    not 1, or a timestamp that does not increase. An empty file gives an empty table."""
    stamps: list[int] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    text = read_text(path, "a TUM trajectory (t x y z qx qy qz qw per line)", error)
    for no, line in data_lines(text):
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise error(
                f"{path}: line {no}: expected 8 numbers (t x y z qx qy qz qw), got {len(fields)}"
            )
        try:
            stamps.append(seconds_text_to_ns(fields[0]))
            rows.append(finite_floats(fields[1:]))
        except ValueError:
            raise error(
                f"{path}: line {no}: expected 8 finite numbers (t x y z qx qy qz qw), "
                f"got {line[:80]!r}"
            ) from None
        lines.append(no)
    check_stamps_increasing(path, stamps, lines, error)
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    _check_unit(path, arr[:, 3:], lines, "qx qy qz qw", error)
    return PoseTable(np.asarray(stamps, dtype=np.int64), arr[:, :3].copy(), arr[:, 3:].copy())


def _check_unit(
    path: Path, q: F64, lines: list[int], columns: str, error: type[CvslamError]
) -> None:
    """`error` naming the file and line of the first quaternion whose norm is not 1."""
    norms = np.linalg.norm(q, axis=1)
    bad = first_non_unit(norms)
    if bad is not None:
        raise error(
            f"{path}: line {lines[bad]}: quaternion norm {norms[bad]:.4f} is not 1 "
            f"(expected {columns} in columns 5-8)"
        )


def write_kitti(path: Path, table: PoseTable) -> None:
    """Write `table` in the KITTI pose format: per pose the row-major 3x4 [R | t] of
    `T_world_body` (12 numbers, shortest text that reads back to the same float). The
    format has no stamps: keep them elsewhere (the TUM file) and give them to `read_kitti`.
    Temporary name, renamed when complete."""
    R = quat_xyzw_to_matrix(np.asarray(table.q_nav_body_xyzw, dtype=np.float64).reshape(-1, 4))
    T = np.concatenate([R, np.asarray(table.p_nav_m, dtype=np.float64).reshape(-1, 3, 1)], axis=2)
    lines = [" ".join(repr(float(v)) for v in m.reshape(12)) for m in T]
    write_text_atomic(path, "".join(line + "\n" for line in lines))


def read_kitti(path: Path, stamps_ns: I64 | None = None) -> PoseTable:
    """Read a KITTI pose file (12 numbers per line, row-major 3x4 `T_world_body`; blank and
    '#' lines skipped). The file has no stamps: `stamps_ns` (N,) gives them, one per pose;
    without it pose i gets stamp i seconds (i * 10^9 ns). Rotations are re-orthonormalised
    (KITTI files carry about 6 digits); one departing from a rotation by more than 0.01
    (Frobenius), or a malformed line, is a `CvslamError` naming the file and line."""
    rows: list[list[float]] = []
    lines: list[int] = []
    for no, line in data_lines(read_text(path, "a KITTI pose file (12 numbers per line)")):
        fields = line.split()
        if len(fields) != 12:
            raise CvslamError(
                f"{path}: line {no}: expected 12 numbers (row-major 3x4 pose), got {len(fields)}"
            )
        try:
            rows.append(finite_floats(fields))
        except ValueError:
            raise CvslamError(
                f"{path}: line {no}: expected 12 finite numbers, got {line[:80]!r}"
            ) from None
        lines.append(no)
    T = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    R = np.empty((len(T), 3, 3))
    for k, m in enumerate(T):
        R[k] = nearest_rotation(m[:, :3])
        err = float(np.linalg.norm(R[k] - m[:, :3]))
        if not err <= _ROTATION_TOL or np.linalg.det(m[:, :3]) <= 0:
            raise CvslamError(
                f"{path}: line {lines[k]}: the left 3x3 block is not a rotation "
                f"(distance {err:.3g} from the nearest one)"
            )
    if stamps_ns is None:
        stamps = np.arange(len(T), dtype=np.int64) * 1_000_000_000
    else:
        try:
            given = check_shape("stamps_ns", stamps_ns, ("poses",), "iu", {"poses": len(T)})
        except ValueError as exc:
            raise CvslamError(
                f"{path}: {len(T)} poses, but the stamps given do not fit: {exc}"
            ) from None
        stamps = given.astype(np.int64)
        check_stamps_increasing(path, stamps, lines)
    q = matrix_to_quat_xyzw(R) if len(T) else np.empty((0, 4))
    return PoseTable(stamps, T[:, :, 3].copy(), q.reshape(-1, 4))


EUROC_HEADER = (
    "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
)


def write_euroc_csv(path: Path, table: PoseTable) -> None:
    """Write `table` as an EuRoC ground-truth style CSV (`EUROC_HEADER`: integer ns stamp,
    position, quaternion w x y z; the shortest text that reads back to the same float), what
    `evo_ape euroc` and `read_euroc_csv` read. Temporary name, renamed when complete."""
    lines = [EUROC_HEADER]
    for t, p, q in zip(table.stamps_ns, table.p_nav_m, table.q_nav_body_xyzw, strict=True):
        values = (*p, q[3], q[0], q[1], q[2])
        lines.append(f"{int(t)}," + ",".join(repr(float(v)) for v in values))
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_euroc_csv(path: Path, error: type[CvslamError] = CvslamError) -> PoseTable:
    """Read an EuRoC ground-truth CSV (`t_ns, px, py, pz, qw, qx, qy, qz[, ...]` per line):
    integer-nanosecond stamps, the quaternion reordered to x y z w. `error` naming the file
    and line for a malformed line, a non-unit quaternion or stamps that do not increase."""
    stamps: list[int] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    text = read_text(path, "an EuRoC ground-truth CSV (t_ns, p xyz, q wxyz, ...)", error)
    for no, line in data_lines(text):
        fields = [f.strip() for f in line.split(",")]
        try:
            if len(fields) < 8:
                raise ValueError
            stamps.append(int(fields[0]))
            rows.append(finite_floats(fields[1:8]))
        except ValueError:
            raise error(
                f"{path}: line {no}: expected t_ns, px, py, pz, qw, qx, qy, qz (comma-separated), "
                f"got {line[:80]!r}"
            ) from None
        lines.append(no)
    check_stamps_increasing(path, stamps, lines, error)
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    q_xyzw = arr[:, [4, 5, 6, 3]]
    _check_unit(path, q_xyzw, lines, "qw qx qy qz", error)
    return PoseTable(np.asarray(stamps, dtype=np.int64), arr[:, :3].copy(), q_xyzw.copy())


def read_trajectory_file(path: Path) -> PoseTable:
    """A TUM (8 numbers per line), KITTI (12) or EuRoC CSV (comma-separated, integer
    nanosecond stamps, 8 or more columns) file, told apart by its first data line."""
    lines = data_lines(read_text(path, "a trajectory (TUM, KITTI or EuRoC CSV file)"))
    first = next((line for _, line in lines), "")
    fields = first.replace(",", " ").split()
    if len(fields) == 12 and "," not in first:
        return read_kitti(path)
    ns_stamp = bool(fields) and fields[0].isdigit() and (len(fields) > 8 or len(fields[0]) >= 16)
    if "," in first and len(fields) >= 8 and ns_stamp:
        return read_euroc_csv(path)
    return read_tum(path)
