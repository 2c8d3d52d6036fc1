"""The output files of `cvslam fuse` (DESIGN.md section 5; described in docs/fuse_outputs.md).

- `map.csv`: the landmark map in full precision (`write_map_csv` / `read_map_csv`, exact);
- `map.ply`: the same map as a binary point cloud for CloudCompare, MeshLab, Open3D;
- pose covariance `.npz`: the 6x6 covariance of each estimated pose (versioned format);
- (`result.mcap`, the viewer log, is written by `io/result_mcap.py`);
- `write_csv_atomic`: any table (timeline, events) as CSV, floats that read back exactly.

Every writer is atomic (`io/atomic.py`); every reader raises a
one-line `CvslamError` naming the file for anything it cannot use.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pandas as pd

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.atomic import write_bytes_atomic, write_text_atomic
from cvslam_cli.io.npz import load_versioned_npz, save_npz
from cvslam_cli.io.textfiles import read_text
from cvslam_cli.records.arrays import F64, I32, I64, check_shape
from cvslam_cli.records.landmarks import UNKNOWN_TRUE_ID, LandmarkMap

# -- CSV ------------------------------------------------------------------------------------


def write_csv_atomic(path: Path, frame: pd.DataFrame) -> None:
    """Write `frame` as CSV (no index column, `\\n` line ends, NaN as `nan`) to
    `path` atomically. Floats are written as the shortest text that reads back
    to the same float64 (pandas' default `repr` formatting, kept explicitly)."""
    text = frame.to_csv(index=False, lineterminator="\n", float_format=None, na_rep="nan")
    write_text_atomic(path, text)


# -- the landmark map -----------------------------------------------------------------------

MAP_COLUMNS = (
    "id",
    "x_m",
    "y_m",
    "z_m",
    "std_x_m",
    "std_y_m",
    "std_z_m",
    "observers",
    "n_observations",
    "first_seen_ns",
    "last_seen_ns",
    "in_state",
    "session",
)
SESSION_COLUMN = "session"  # written; a file without it (earlier runs) reads as session 0
TRUE_ID_COLUMN = "true_id"  # read when present; `write_map_csv` does not write it
OBSERVER_SEPARATOR = ";"


def map_frame(table: LandmarkMap) -> pd.DataFrame:
    """`table` as a DataFrame with the `map.csv` columns (`MAP_COLUMNS`)."""
    return pd.DataFrame(
        {
            "id": table.landmark_id,
            "x_m": table.p_nav_m[:, 0],
            "y_m": table.p_nav_m[:, 1],
            "z_m": table.p_nav_m[:, 2],
            "std_x_m": table.std_m[:, 0],
            "std_y_m": table.std_m[:, 1],
            "std_z_m": table.std_m[:, 2],
            "observers": pd.Series(table.observers, dtype=object),
            "n_observations": table.n_observations,
            "first_seen_ns": table.first_seen_ns,
            "last_seen_ns": table.last_seen_ns,
            "in_state": table.in_state,
            "session": table.session,
        },
        columns=list(MAP_COLUMNS),
    )


def write_map_csv(path: Path, table: LandmarkMap) -> None:
    """Write `map.csv` (columns `MAP_COLUMNS`, one landmark per row, floats exact,
    `in_state` as True/False). `read_map_csv` gives back an equal table."""
    write_csv_atomic(path, map_frame(table))


_BOOL_TEXT = {"true": True, "1": True, "false": False, "0": False}


def read_map_csv(path: Path) -> LandmarkMap:
    """Read `map.csv` as written by `write_map_csv` (extra columns are ignored; column order
    is free). The simulator ids come from a `true_id` column when the file has one, else
    they are unknown (-1). `CvslamError` naming the file, and the column and line, for
    anything unusable."""
    text = read_text(path, "a landmark map CSV (map.csv)")
    reader = csv.reader(io.StringIO(text))
    rows = [(reader.line_num, r) for r in reader if r]  # (line number, fields), blanks skipped
    if not rows:
        raise CvslamError(f"{path}: empty file, expected a header row {','.join(MAP_COLUMNS)}")
    head = [h.strip() for h in rows[0][1]]
    missing = [c for c in MAP_COLUMNS if c not in head and c != SESSION_COLUMN]
    if missing:
        raise CvslamError(
            f"{path}: missing column(s) {', '.join(missing)} (expected {','.join(MAP_COLUMNS)})"
        )
    body = rows[1:]
    for no, r in body:
        if len(r) != len(head):
            raise CvslamError(f"{path}: line {no}: {len(r)} fields, the header has {len(head)}")
    index = {c: head.index(c) for c in (*MAP_COLUMNS, TRUE_ID_COLUMN) if c in head}

    def column(name: str, parse: type[int] | type[float]) -> list[int] | list[float]:
        out = []
        for no, r in body:
            cell = r[index[name]].strip()
            try:
                out.append(parse(cell))
            except ValueError:
                what = "an integer" if parse is int else "a number"
                raise CvslamError(
                    f"{path}: line {no}: column {name}: expected {what}, got {cell!r}"
                ) from None
        return out

    in_state = []
    for no, r in body:
        cell = r[index["in_state"]].strip().lower()
        if cell not in _BOOL_TEXT:
            raise CvslamError(
                f"{path}: line {no}: column in_state: expected True or False, "
                f"got {r[index['in_state']]!r}"
            )
        in_state.append(_BOOL_TEXT[cell])

    def floats(*names: str) -> F64:
        return np.array([column(n, float) for n in names], dtype=np.float64).T.reshape(-1, 3)

    try:
        return LandmarkMap(
            landmark_id=np.array(column("id", int), dtype=np.int64),
            p_nav_m=floats("x_m", "y_m", "z_m"),
            std_m=floats("std_x_m", "std_y_m", "std_z_m"),
            observers=tuple(r[index["observers"]] for _, r in body),
            n_observations=np.array(column("n_observations", int), dtype=np.int64),
            first_seen_ns=np.array(column("first_seen_ns", int), dtype=np.int64),
            last_seen_ns=np.array(column("last_seen_ns", int), dtype=np.int64),
            in_state=np.array(in_state, dtype=bool),
            true_id=np.array(column(TRUE_ID_COLUMN, int), dtype=np.int64)
            if TRUE_ID_COLUMN in index
            else np.full(len(body), UNKNOWN_TRUE_ID, dtype=np.int64),
            session=np.array(column(SESSION_COLUMN, int), dtype=np.int64)
            if SESSION_COLUMN in index
            else None,
        )
    except (ValueError, OverflowError) as exc:
        raise CvslamError(f"{path}: not a usable map ({exc})") from None


# -- PLY ------------------------------------------------------------------------------------

PLY_VERTEX_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<i4"), ("std", "<f4"), ("n_obs", "<i4")]
)
_PLY_TYPES = {"<f4": "float", "<i4": "int"}
_INT32 = np.iinfo(np.int32)


def _int32_column(name: str, values: I64) -> I32:
    if values.size and (values.min() < _INT32.min or values.max() > _INT32.max):
        raise ValueError(f"{name}: values outside the int32 range of the PLY/point cloud field")
    return values.astype(np.int32)


def map_vertices(table: LandmarkMap) -> np.ndarray:
    """(N,) structured array `PLY_VERTEX_DTYPE`: x y z (float32, nav frame, m), id,
    std (float32, the largest of the three standard deviations, m), n_obs."""
    v = np.empty(len(table), dtype=PLY_VERTEX_DTYPE)
    v["x"], v["y"], v["z"] = (table.p_nav_m[:, k].astype(np.float32) for k in range(3))
    v["id"] = _int32_column("landmark id", table.landmark_id)
    v["std"] = table.max_std_m.astype(np.float32)
    v["n_obs"] = _int32_column("n_observations", table.n_observations)
    return v


def write_map_ply(path: Path, table: LandmarkMap) -> None:
    """Write `map.ply`: binary little-endian PLY 1.0, one `vertex` element per landmark with
    float x y z, int id, float std (largest of the 3 std devs, m), int n_obs. Positions are
    float32 (mm-level at km range): `map.csv` has them in full precision."""
    vertices = map_vertices(table)
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        "comment cvslam landmark map: nav frame (NED), metres",
        "comment std: largest of the 3 position standard deviations [m]; n_obs: observations",
        f"element vertex {len(vertices)}",
        *(
            f"property {_PLY_TYPES[PLY_VERTEX_DTYPE.fields[name][0].str]} {name}"
            for name in PLY_VERTEX_DTYPE.names or ()
        ),
        "end_header",
    ]
    data = ("\n".join(lines) + "\n").encode("ascii") + vertices.tobytes()
    write_bytes_atomic(path, data)


# -- pose covariances -----------------------------------------------------------------------

POSE_COV_FORMAT = "cvslam.pose_covariance"
POSE_COV_VERSION = 1
POSE_COV_COMPONENTS = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")


def _check_pose_cov(stamps_ns: np.ndarray, cov: np.ndarray) -> None:
    dims: dict[str, int] = {}
    check_shape("pose covariances: stamps_ns", stamps_ns, ("F",), "iu", dims)
    check_shape("pose covariances: cov", cov, ("F", 6, 6), "iuf", dims)


def save_pose_covariances(path: Path, stamps_ns: I64, cov: F64) -> None:
    """Write the covariance of each estimated pose: `stamps_ns` (F,) int64, `cov` (F, 6, 6)
    float64 over (x, y, z [m] in the nav frame, roll, pitch, yaw [rad], ZYX Euler). An
    uncompressed, byte-reproducible .npz with `format`, `version` and `components` entries."""
    stamps = np.asarray(stamps_ns)
    c = np.asarray(cov)
    _check_pose_cov(stamps, c)
    save_npz(
        path,
        {
            "format": np.array(POSE_COV_FORMAT),
            "version": np.array(POSE_COV_VERSION),
            "components": np.array(POSE_COV_COMPONENTS),
            "stamps_ns": stamps.astype(np.int64),
            "cov": c.astype(np.float64),
        },
    )


def load_pose_covariances(path: Path) -> tuple[I64, F64]:
    """(stamps_ns (F,) int64, cov (F, 6, 6) float64) from `save_pose_covariances`'s file.
    `CvslamError` naming the file when it is missing, another format or version, or corrupt."""
    data = load_versioned_npz(
        path, POSE_COV_FORMAT, POSE_COV_VERSION, "pose covariance", "cvslam fuse --force"
    )
    try:
        stamps, cov = data["stamps_ns"], data["cov"]
        _check_pose_cov(stamps, cov)
    except (KeyError, ValueError) as exc:
        raise CvslamError(f"{path}: corrupt pose covariance file ({exc})") from None
    return stamps.astype(np.int64), cov.astype(np.float64)
