"""The map file `map.npz`: a `LandmarkArchive` (every landmark a fuse run mapped, evicted ones
too, with its nav-frame Gaussian, descriptor, observers and times), versioned, read back
exactly. An uncompressed NumPy .npz without pickles, byte-reproducible (`io/npz.py`); its
entries are listed in docs/fuse_outputs.md ("Map file")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.npz import load_versioned_npz, save_npz
from cvslam_cli.io.run_layout import FuseFolder, RunLayout
from cvslam_cli.records.landmark_archive import LandmarkArchive

MAP_FORMAT = "cvslam.map"
MAP_VERSION = 1
NAV_FRAME = "NED"

_ARRAYS = (
    "landmark_id",
    "true_id",
    "p_nav_m",
    "cov_nav_m2",
    "descriptor",
    "view_dir_sum_nav",
    "first_seen_ns",
    "last_seen_ns",
    "n_observations",
    "in_state",
    "evicted_ns",
    "reactivations",
    "session",
    "batch",
)
# entries a file may lack (written by an earlier cvslam of the same version): read as None
_OPTIONAL = ("session", "batch")


def save_map(path: Path, archive: LandmarkArchive) -> None:
    """Write `archive` to `path` (written whole to `<path>.partial`, then renamed)."""
    arrays = {name: getattr(archive, name) for name in _ARRAYS}
    save_npz(
        path,
        {
            "format": np.array(MAP_FORMAT),
            "version": np.array(MAP_VERSION),
            "nav_frame": np.array(NAV_FRAME),
            "vehicles": np.array(archive.vehicles, dtype=str),
            "coordinates": np.array(archive.coordinates),
            **arrays,
        },
    )


def load_map(path: Path) -> LandmarkArchive:
    """The archive `save_map` wrote. `CvslamError` naming the file when it is missing, of
    another format or version, or its arrays do not fit together."""
    data = load_versioned_npz(path, MAP_FORMAT, MAP_VERSION, "map", "cvslam fuse --force")
    try:
        if str(data["nav_frame"]) != NAV_FRAME:
            raise ValueError(f"nav frame {str(data['nav_frame'])!r}, expected {NAV_FRAME!r}")
        return LandmarkArchive(
            vehicles=tuple(str(v) for v in data["vehicles"].reshape(-1)),
            coordinates=str(data["coordinates"]),
            **{name: data[name] for name in _ARRAYS if name in data or name not in _OPTIONAL},
        )
    except (KeyError, ValueError) as exc:
        raise CvslamError(f"{path}: corrupt map file ({exc})") from None


def prior_map_path(spec: str) -> Path:
    """The map file `fuse.prior_map` names: a run directory's `fuse/map.npz`, the
    `map.npz` of a fuse folder (`RUN/fuse_refined`, ...), or a map file itself.
    `CvslamError` naming the key and the path when none exists."""
    path = Path(spec).expanduser()
    if path.is_dir() and FuseFolder(path).map_npz.is_file():
        return FuseFolder(path).map_npz
    if path.is_dir():
        found = RunLayout(path).fuse().map_npz
        if not found.is_file():
            raise CvslamError(
                f"fuse.prior_map: {path} is a folder without {found.relative_to(path)} (expected "
                f"a run directory fused with this cvslam, `cvslam fuse {path}`, a fuse folder "
                "holding a map.npz, or a map.npz)"
            )
        return found
    if not path.exists():
        raise CvslamError(f"fuse.prior_map: {path}: no such run directory or map file")
    return path


def load_prior_map(spec: str) -> tuple[Path, LandmarkArchive]:
    """(the map file, its archive) of `fuse.prior_map` (`prior_map_path`, `load_map`)."""
    path = prior_map_path(spec)
    return path, load_map(path)
