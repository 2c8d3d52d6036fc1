"""`<fuse folder>/observations.npz`: every landmark observation a filter run used
(`records.observations.ObservationTable`; docs/fuse_outputs.md), the input of `cvslam refine`.
An uncompressed, byte-reproducible .npz (no pickles)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.npz import load_versioned_npz, save_npz
from cvslam_cli.records.observations import ObservationTable

FORMAT = "cvslam.observations"
VERSION = 1


def save_observations(path: Path, table: ObservationTable) -> None:
    """Write `table`, sorted by (vehicle, stamp, landmark id): the same table, the same bytes."""
    order = np.lexsort((table.landmark_id, table.stamp_ns, table.vehicle))
    save_npz(
        path,
        {
            "format": np.array(FORMAT),
            "version": np.array(VERSION),
            "vehicles": np.array(table.vehicles, dtype=str).reshape(-1),
            "vehicle": table.vehicle[order].astype(np.int64),
            "stamp_ns": table.stamp_ns[order].astype(np.int64),
            "landmark_id": table.landmark_id[order].astype(np.int64),
            "z_px": table.z_px[order].astype(np.float64),
        },
    )


def load_observations(path: Path) -> ObservationTable:
    """The table `save_observations` wrote; `CvslamError` naming the file otherwise."""
    data = load_versioned_npz(path, FORMAT, VERSION, "observation", "cvslam fuse --force")
    try:
        return ObservationTable(
            tuple(str(v) for v in data["vehicles"].reshape(-1)),
            data["vehicle"].astype(np.int64),
            data["stamp_ns"].astype(np.int64),
            data["landmark_id"].astype(np.int64),
            data["z_px"].astype(np.float64),
        )
    except (KeyError, ValueError) as exc:
        raise CvslamError(f"{path}: corrupt observation file ({exc})") from None
