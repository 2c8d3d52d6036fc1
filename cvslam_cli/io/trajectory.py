"""Trajectory tables and files.

TUM format (what evo reads): one pose per line, `t x y z qx qy qz qw`, t in seconds; cvslam
writes t exactly from integer nanoseconds (9 decimals, no float rounding) and the pose of
the body in the nav frame (NED). `read_tum` parses t back to integer nanoseconds from the
decimal text (never through a float), so `read_tum(write_tum(table))` has the same stamps and
the values to the 9 written decimals.

KITTI pose format (what evo reads with `evo_traj kitti`): one pose per line, the 12 numbers
of the row-major 3x4 matrix [R | t] of `T_world_body`, no stamps and no comments.
"""

from __future__ import annotations

from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.records.arrays import F64, I64, check_shape
from cvslam_cli.records.poses import PoseTable


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
    write_text_atomic(path, "\n".join(lines) + "\n")


# -- reading TUM, KITTI --------------------------------------------------------------------

_NS_PER_S = Decimal(1_000_000_000)
_QUAT_NORM_TOL = 1e-2
_ROTATION_TOL = 1e-2


def seconds_text_to_ns(text: str) -> int:
    """Decimal seconds as text ("1403715273.262142976", "1.5e-3") -> integer nanoseconds,
    rounded half to even, without going through a float. ValueError when not finite."""
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise ValueError(f"not a number: {text!r}") from None
    if not value.is_finite():
        raise ValueError(f"not a finite number: {text!r}")
    return int((value * _NS_PER_S).to_integral_value(rounding=ROUND_HALF_EVEN))


def _read_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """(line number, stripped text) of the data lines: blank and '#' lines skipped."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CvslamError(f"{path}: file not found, expected {what}") from None
    except IsADirectoryError:
        raise CvslamError(f"{path}: is a directory, expected {what}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CvslamError(f"{path}: cannot be read as {what} ({exc})") from None
    out = []
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            out.append((no, line))
    return out


def finite_floats(fields: list[str]) -> list[float]:
    values = [float(f) for f in fields]
    if not all(np.isfinite(values)):
        raise ValueError("not finite")
    return values


def _check_increasing(path: Path, stamps: list[int], lines: list[int]) -> None:
    for k in range(1, len(stamps)):
        if stamps[k] <= stamps[k - 1]:
            raise CvslamError(
                f"{path}: line {lines[k]}: timestamp {ns_to_seconds_text(stamps[k])} s "
                f"does not increase (previous {ns_to_seconds_text(stamps[k - 1])} s)"
            )


def read_tum(path: Path) -> PoseTable:
    """Read a TUM file (`t x y z qx qy qz qw` per line, whitespace or commas, '#' comments):
    the inverse of `write_tum`. Stamps are parsed exactly from the decimal text (rounded
    half to even to ns beyond 9 decimals); values are kept as written (no renormalisation).
    `CvslamError` naming the file and line for a malformed line, a quaternion whose norm is
    not 1, or a timestamp that does not increase. An empty file gives an empty table."""
    stamps: list[int] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    for no, line in _read_lines(path, "a TUM trajectory (t x y z qx qy qz qw per line)"):
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise CvslamError(
                f"{path}: line {no}: expected 8 numbers (t x y z qx qy qz qw), got {len(fields)}"
            )
        try:
            stamps.append(seconds_text_to_ns(fields[0]))
            rows.append(finite_floats(fields[1:]))
        except ValueError:
            raise CvslamError(
                f"{path}: line {no}: expected 8 finite numbers (t x y z qx qy qz qw), "
                f"got {line[:80]!r}"
            ) from None
        lines.append(no)
    _check_increasing(path, stamps, lines)
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    norms = np.linalg.norm(arr[:, 3:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _QUAT_NORM_TOL)
    if bad.size:
        raise CvslamError(
            f"{path}: line {lines[bad[0]]}: quaternion norm {norms[bad[0]]:.4f} is not 1 "
            "(expected qx qy qz qw in columns 5-8)"
        )
    return PoseTable(np.asarray(stamps, dtype=np.int64), arr[:, :3].copy(), arr[:, 3:].copy())


def write_kitti(path: Path, table: PoseTable) -> None:
    """Write `table` in the KITTI pose format: per pose the row-major 3x4 [R | t] of
    `T_world_body` (12 numbers, shortest text that reads back to the same float). The
    format has no stamps: keep them elsewhere (the TUM file) and give them to `read_kitti`.
    Temporary name, renamed when complete."""
    R = quat_xyzw_to_matrix(np.asarray(table.q_xyzw, dtype=np.float64).reshape(-1, 4))
    T = np.concatenate([R, np.asarray(table.p_m, dtype=np.float64).reshape(-1, 3, 1)], axis=2)
    lines = [" ".join(repr(float(v)) for v in m.reshape(12)) for m in T]
    write_text_atomic(path, "".join(line + "\n" for line in lines))


def _nearest_rotation(R: F64) -> F64:
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def read_kitti(path: Path, stamps_ns: I64 | None = None) -> PoseTable:
    """Read a KITTI pose file (12 numbers per line, row-major 3x4 `T_world_body`; blank and
    '#' lines skipped). The file has no stamps: `stamps_ns` (N,) gives them, one per pose;
    without it pose i gets stamp i seconds (i * 10^9 ns). Rotations are re-orthonormalised
    (KITTI files carry about 6 digits); one departing from a rotation by more than 0.01
    (Frobenius), or a malformed line, is a `CvslamError` naming the file and line."""
    rows: list[list[float]] = []
    lines: list[int] = []
    for no, line in _read_lines(path, "a KITTI pose file (12 numbers per line)"):
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
        R[k] = _nearest_rotation(m[:, :3])
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
        if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
            k = int(np.flatnonzero(np.diff(stamps) <= 0)[0]) + 1
            raise CvslamError(
                f"{path}: the stamp given for line {lines[k]} does not increase "
                f"({ns_to_seconds_text(int(stamps[k]))} s after "
                f"{ns_to_seconds_text(int(stamps[k - 1]))} s)"
            )
    q = matrix_to_quat_xyzw(R) if len(T) else np.empty((0, 4))
    return PoseTable(stamps, T[:, :, 3].copy(), q.reshape(-1, 4))
