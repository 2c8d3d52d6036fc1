"""`cvslam export`: a run's estimates in the frame and file format the user's tools expect
(docs/export.md), so that evo's APE and RPE against a dataset's own ground truth are right.

Frames (`geometry/output_frames.py`):
- `nav`: as fuse writes them, `T_nav_body` (NED nav frame, the vehicle's body frame);
- `enu`: `T_enu_body`, the z-up frame beside nav (x east, y north, z up), body unchanged;
- `dataset`: `T_world_sensor`, the pose of the sensor the dataset's ground truth is about in
  the dataset's world (KITTI: camera 0 in the poses.txt world, so that the first pose is the
  identity like poses.txt's, up to the window's later estimate of it; EuRoC: the IMU body
  in the Vicon world), undoing the conversion the importer recorded in each log
  (`io/dataset_frames.py`). Logs without one
  (simulations, recordings) are refused with one line naming the run and the log.
Formats: `tum` (`<v>.tum`: t x y z qx qy qz qw), `kitti` (`<v>.txt`: 12 numbers per pose,
row-major 3x4, and `<v>_times.txt`: the stamp of each line in seconds), `euroc`
(`<v>.csv`: ns stamp, position, quaternion w x y z).

Every table is converted before the first file is written, and each file is written
atomically.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cvslam_cli.config import Config, LogsConfig
from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.output_frames import T_ENU_NAV, reexpress
from cvslam_cli.io.atomic import check_writable, write_text_atomic
from cvslam_cli.io.dataset_frames import log_dataset_frames
from cvslam_cli.io.features_file import feature_frame_index
from cvslam_cli.io.logs import all_log_paths, require_logs, with_run_bindings
from cvslam_cli.io.run_layout import FUSE, FuseFolder, RunLayout
from cvslam_cli.io.textfiles import ns_to_seconds_text
from cvslam_cli.io.trajectory import read_tum, write_euroc_csv, write_kitti, write_tum
from cvslam_cli.records.poses import PoseTable

FORMATS = ("tum", "kitti", "euroc")
FRAMES = ("nav", "enu", "dataset")


@dataclass(frozen=True, eq=False)
class VehicleExport:
    """One vehicle's exported estimate: its `table` in the asked frame, what its poses
    are (`world`, `sensor`, in words), and the files written."""

    table: PoseTable
    world: str
    sensor: str
    files: tuple[Path, ...] = ()


@dataclass(frozen=True)
class ExportSummary:
    out_dir: Path
    source: str
    frame: str
    format: str
    vehicles: dict[str, VehicleExport]


def _source_folder(layout: RunLayout, source: str) -> FuseFolder:
    """The fuse folder `source`; CvslamError listing the run's fuse folders otherwise."""
    folders = layout.fuse_folders()
    for f in folders:
        if f.name == source:
            return f
    have = ", ".join(f.name for f in folders) or "none (run `cvslam fuse` first)"
    raise CvslamError(f"{layout.root}: no estimates in {source}/ (fuse folders: {have})")


def _run_logs(logs_cfg: LogsConfig, layout: RunLayout, log_paths: Sequence[Path]) -> list[Path]:
    """`log_paths` and the logs bound to vehicles; with neither, the logs the run's
    features came from. Each must exist."""
    if not log_paths and not any(v.log for v in logs_cfg.vehicles.values()):
        _, metas = feature_frame_index(layout.root)
        log_paths = layout.find_logs(metas)
    paths = all_log_paths(list(log_paths), logs_cfg)
    require_logs(paths)
    return paths


def _in_dataset_frames(
    cfg: Config, layout: RunLayout, tables: dict[str, PoseTable], log_paths: Sequence[Path]
) -> dict[str, VehicleExport]:
    """Each of `tables` in its log's dataset frame: the log bound to the vehicle
    (`logs.vehicles.<v>.log`, NAME=PATH, or as extract recorded it), else the log imported
    under the vehicle's name."""
    logs_cfg = with_run_bindings(cfg.logs, layout.root)
    logs = _run_logs(logs_cfg, layout, log_paths)
    imported = log_dataset_frames(logs)
    out = {}
    for v, table in tables.items():
        bound = logs_cfg.vehicles[v].log if v in logs_cfg.vehicles else ""
        mine = [p for p in imported if bound and p.resolve() == Path(bound).resolve()]
        mine = mine or [p for p, (name, _) in imported.items() if name == v]
        frame = imported[mine[0]][1] if mine else None
        if frame is None:
            where = (
                f"its log {mine[0]} records"
                if mine
                else (f"its logs ({', '.join(map(str, logs))}) record")
            )
            raise CvslamError(
                f"{layout.root}: --frame dataset: vehicle {v}: {where} no dataset frame "
                "(a simulated or recorded log, or imported by an older cvslam: re-import it); "
                "use --frame nav or enu"
            )
        out[v] = VehicleExport(
            reexpress(table, frame.T_world_nav, frame.T_body_sensor), frame.world, frame.sensor
        )
    return out


def convert(
    cfg: Config,
    layout: RunLayout,
    tables: dict[str, PoseTable],
    frame: str,
    log_paths: Sequence[Path] = (),
) -> dict[str, VehicleExport]:
    """Each of `tables` (poses `T_nav_body`) in `frame` (module docstring)."""
    if frame == "dataset":
        return _in_dataset_frames(cfg, layout, tables, log_paths)
    T_world_nav = T_ENU_NAV if frame == "enu" else np.eye(4)
    world = "ENU (x east, y north, z up)" if frame == "enu" else "nav (NED)"
    return {
        v: VehicleExport(reexpress(t, T_world_nav, np.eye(4)), world, "body")
        for v, t in tables.items()
    }


def files_of(out_dir: Path, vehicle: str, fmt: str) -> tuple[Path, ...]:
    """The files `fmt` writes for `vehicle` (module docstring)."""
    if fmt == "kitti":
        return out_dir / f"{vehicle}.txt", out_dir / f"{vehicle}_times.txt"
    return (out_dir / f"{vehicle}.{'csv' if fmt == 'euroc' else 'tum'}",)


def _write(files: tuple[Path, ...], vehicle: str, e: VehicleExport, fmt: str, source: str) -> None:
    if fmt == "tum":
        header = f"cvslam export of {source}/{vehicle}.tum: pose of the {e.sensor} in {e.world}"
        write_tum(files[0], e.table, header=header)
    elif fmt == "euroc":
        write_euroc_csv(files[0], e.table)
    else:
        write_kitti(files[0], e.table)
        times = "".join(ns_to_seconds_text(int(t)) + "\n" for t in e.table.stamps_ns)
        write_text_atomic(files[1], times)


def run(
    cfg: Config,
    run_dir: Path,
    *,
    source: str = FUSE,
    fmt: str = "tum",
    frame: str = "nav",
    out_dir: Path | None = None,
    log_paths: Sequence[Path] = (),
) -> ExportSummary:
    """Export every vehicle's estimate of fuse folder `source` of `run_dir` in `frame` and
    format `fmt` to `out_dir` (default `<run>/export/<source>_<frame>/`)."""
    if fmt not in FORMATS or frame not in FRAMES:
        raise CvslamError(
            f"export: format {fmt!r} / frame {frame!r}: expected {FORMATS} / {FRAMES}"
        )
    layout = RunLayout(Path(run_dir))
    folder = _source_folder(layout, source)
    tables = {v: read_tum(folder.trajectory(v)) for v in folder.vehicles()}
    exports = convert(cfg, layout, tables, frame, log_paths)
    out = Path(out_dir) if out_dir is not None else layout.export_dir(source, frame)
    written = {v: dataclasses.replace(e, files=files_of(out, v, fmt)) for v, e in exports.items()}
    check_writable([f for e in written.values() for f in e.files])
    for v, e in written.items():
        _write(e.files, v, e, fmt, source)
    return ExportSummary(out, source, frame, fmt, written)
