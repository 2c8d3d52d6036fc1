"""The dataset frame an importer records in a log's `cvslam.import` metadata, and finding it
again for `cvslam export --frame dataset` (docs/export.md).

An importer converts the dataset's world frame to the NED nav frame once, at import
(`io/importers/`); these keys say how, as numbers, so that the conversion can be undone:
- `dataset_world_frame`, `dataset_sensor_frame`: their names in words;
- `T_nav_world`: JSON 4x4, dataset world -> nav (p_nav = T_nav_world p_world);
- `T_body_sensor`: JSON 4x4, the sensor whose pose the dataset's ground truth gives, in the
  vehicle's body frame (KITTI: camera 0; EuRoC: the IMU, the identity).
Logs of the simulator (or imported by an older cvslam) have no such keys.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.output_frames import DatasetFrame
from cvslam_cli.io.log_open import open_log

IMPORT_RECORD = "cvslam.import"
WORLD_KEY, SENSOR_KEY = "dataset_world_frame", "dataset_sensor_frame"
T_NAV_WORLD_KEY, T_BODY_SENSOR_KEY = "T_nav_world", "T_body_sensor"


def dataset_frame_fields(frame: DatasetFrame) -> dict[str, str]:
    """The metadata entries of `frame` (module docstring)."""
    return {
        WORLD_KEY: frame.world,
        SENSOR_KEY: frame.sensor,
        T_NAV_WORLD_KEY: json.dumps(np.asarray(frame.T_nav_world).tolist()),
        T_BODY_SENSOR_KEY: json.dumps(np.asarray(frame.T_body_sensor).tolist()),
    }


def dataset_frame_of(record: Mapping[str, str], where: str) -> DatasetFrame | None:
    """The `DatasetFrame` of a `cvslam.import` record, None when it has none (an older
    import); `CvslamError` naming `where` when the entries are there but unusable."""
    if T_NAV_WORLD_KEY not in record:
        return None
    try:
        return DatasetFrame(
            np.array(json.loads(record[T_NAV_WORLD_KEY]), dtype=np.float64),
            np.array(json.loads(record[T_BODY_SENSOR_KEY]), dtype=np.float64),
            record.get(WORLD_KEY, "dataset world"),
            record.get(SENSOR_KEY, "dataset sensor"),
        )
    except (KeyError, ValueError, TypeError) as exc:
        raise CvslamError(
            f"{where}: metadata {IMPORT_RECORD}: unusable dataset frame ({exc}); re-import the "
            "dataset"
        ) from None


def log_dataset_frames(paths: Sequence[Path]) -> dict[Path, tuple[str, DatasetFrame | None]]:
    """For each log at `paths` an importer wrote: the vehicle it was imported as, and its
    dataset frame (None for an import that recorded none). Logs without an import record
    (simulations, recordings) are left out."""
    out: dict[Path, tuple[str, DatasetFrame | None]] = {}
    for path in map(Path, paths):
        record = open_log(path).metadata().get(IMPORT_RECORD)
        if record is not None and record.get("vehicle"):
            out[path] = (record["vehicle"], dataset_frame_of(record, str(path)))
    return out
