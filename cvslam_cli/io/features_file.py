"""Reading and writing feature files (`<run>/features/<vehicle>.npz`).

An uncompressed NumPy .npz archive: one array per `FeatureSet` field, the rig as `rig_*`
arrays, and `format`, `version`, `vehicle`, `meta_json` entries. Loading is a handful of
`np.load` reads (no per-frame parsing). Written to a temporary name and renamed when
complete, byte-reproducible. A file of another format version is refused with a clear message.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.npz import load_versioned_npz, save_npz
from cvslam_cli.io.run_layout import RunLayout
from cvslam_cli.records.features import FORMAT_NAME, FORMAT_VERSION, FeatureSet, RigCalibration

_RIG_FIELDS = ("K", "D", "T_body_cam", "size_px")
_KIND = ("feature", "cvslam extract --force")  # the file in messages, the command redoing it


def save_features(fs: FeatureSet, path: Path, meta: dict[str, Any]) -> None:
    """Write `fs` (validated) with `meta` (JSON-serialisable provenance) to `path`."""
    fs.validate()
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT_NAME),
        "version": np.array(FORMAT_VERSION),
        "vehicle": np.array(fs.vehicle),
        "meta_json": np.array(json.dumps(meta, sort_keys=True)),
        "rig_distortion_model": np.array(fs.rig.distortion_model),
    }
    for name in _RIG_FIELDS:
        arrays[f"rig_{name}"] = getattr(fs.rig, name)
    for f in fields(fs):
        if f.name not in ("vehicle", "rig"):
            arrays[f.name] = getattr(fs, f.name)
    save_npz(path, arrays)


def load_features(path: Path) -> tuple[FeatureSet, dict[str, Any]]:
    """Read a feature file; `CvslamError` naming the file for anything unusable."""
    data = load_versioned_npz(path, FORMAT_NAME, FORMAT_VERSION, *_KIND)
    try:
        rig = RigCalibration(
            distortion_model=str(data["rig_distortion_model"]),
            **{name: data[f"rig_{name}"] for name in _RIG_FIELDS},
        )
        kwargs = {
            f.name: data[f.name] for f in fields(FeatureSet) if f.name not in ("vehicle", "rig")
        }
        fs = FeatureSet(vehicle=str(data["vehicle"]), rig=rig, **kwargs)
        fs.validate()
    except (KeyError, ValueError) as exc:
        raise CvslamError(f"{path}: corrupt feature file ({exc})") from None
    return fs, json.loads(str(data["meta_json"]))


def load_frame_index(path: Path) -> tuple[str, NDArray[np.int64], dict[str, Any]]:
    """(vehicle, frame_stamp_ns (F,), meta) of a feature file, without reading the features."""
    data = load_versioned_npz(
        path, FORMAT_NAME, FORMAT_VERSION, *_KIND, ("vehicle", "frame_stamp_ns", "meta_json")
    )
    try:
        meta = json.loads(str(data["meta_json"]))
    except ValueError as exc:
        raise CvslamError(f"{path}: corrupt feature file ({exc})") from None
    return str(data["vehicle"]), np.asarray(data["frame_stamp_ns"], dtype=np.int64), meta


def feature_frame_index(run_dir: Path) -> tuple[dict[str, NDArray[np.int64]], list[dict[str, Any]]]:
    """({vehicle: frame_stamp_ns}, metas) of every feature file of a run directory."""
    files = RunLayout(run_dir).feature_files("run `cvslam extract` and `cvslam fuse` first")
    stamps, metas = {}, []
    for f in files:
        vehicle, st, meta = load_frame_index(f)
        stamps[vehicle] = st
        metas.append(meta)
    return stamps, metas
