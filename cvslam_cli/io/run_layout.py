"""The layout of a run directory (DESIGN.md section 5): every folder and file name, and how a
stage finds its inputs there. No other module spells these names.

```
<run>/run.yaml                          RunLayout.run_file (stage records, `io/rundir.py`)
<run>/.lock, <run>/cvslam.log           RunLayout.lock_file, log_file (`RunDir.session`)
<run>/features/<v>.npz, <v>_stats.csv   RunLayout.feature_file, feature_stats
<run>/features/extract.config.yaml      RunLayout.extract_config
<run>/fuse*/                            FuseFolder (fuse, fuse_single, fuse_ekf, fuse_ekf_single,
                                        fuse_refined)
<run>/fuse*_diverged_timeline.csv       RunLayout.diverged_timeline
<run>/mosaic*/                          MosaicFolder (mosaic, mosaic_deadreckoning, ...)
<run>/eval/                             EvalFolder
<run>/export/<source>_<frame>/          RunLayout.export_dir (`cvslam export`)
```
A simulator output directory (`SimLayout`) is a run directory too (`cvslam fuse SIM_OUT`):
the logs, `scenario.yaml` and `truth/` beside `features/` (landmark mode).

Stages are recorded in run.yaml under the name of the folder they write (`EXTRACT_STAGE` for
the features). Writes go through `io/atomic.py`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cvslam_cli.errors import CvslamError

RUN_FILE = "run.yaml"
LOCK_FILE = ".lock"  # held by the one process working on the run directory
LOG_FILE = "cvslam.log"  # the log lines of every command run on the directory, appended
FEATURES = "features"
EXTRACT_STAGE = "extract"
TRUTH = "truth"
EVAL = "eval"
EXPORT = "export"
MERGED_MOSAIC = "all"  # the mosaic of all vehicles, beside one per vehicle
DEADRECKONING = "deadreckoning"  # the trajectory of the motion input without corrections
_CONFIG_SUFFIX = ".config.yaml"
_LOG_SUFFIX = ".mcap"


def fuse_name(filter_kind: str = "hinf", single: bool = False) -> str:
    """`fuse` for the default (cooperative NH-infinity); `fuse_ekf`, `fuse_single`,
    `fuse_ekf_single` for the comparison runs."""
    return (
        "fuse"
        + ("" if filter_kind == "hinf" else f"_{filter_kind}")
        + ("_single" if single else "")
    )


FUSE = fuse_name()
FUSE_SINGLE = fuse_name(single=True)
FUSE_EKF = fuse_name("ekf")
FUSE_EKF_SINGLE = fuse_name("ekf", single=True)


def refined_name(source: str = "fuse") -> str:
    """The folder `cvslam refine` writes for a fuse folder: `fuse_refined` for `fuse`,
    `<source>_refined` otherwise (`fuse_ekf_refined`, ...)."""
    return f"{source}_refined"


FUSE_REFINED = refined_name()


def mosaic_name(source: str = "fused") -> str:
    """`mosaic` for fused poses; `mosaic_deadreckoning`, `mosaic_groundtruth` otherwise."""
    return "mosaic" if source == "fused" else f"mosaic_{source}"


MOSAIC = mosaic_name()


def resolved_config_beside(output: Path) -> Path:
    """Where the resolved config of a written file goes: `<stem>.config.yaml` beside it."""
    return output.with_name(output.stem + _CONFIG_SUFFIX)


@dataclass(frozen=True)
class FuseFolder:
    """The outputs of one `cvslam fuse` run (docs/fuse_outputs.md)."""

    path: Path

    @property
    def name(self) -> str:
        return self.path.name

    def trajectory(self, vehicle: str, *, deadreckoning: bool = False) -> Path:
        """`<v>.tum`, the estimate; `<v>_deadreckoning.tum` with `deadreckoning`."""
        return self.path / (f"{vehicle}_{DEADRECKONING}.tum" if deadreckoning else f"{vehicle}.tum")

    def pose_covariances(self, vehicle: str) -> Path:
        return self.path / f"{vehicle}_pose_cov.npz"

    @property
    def map_csv(self) -> Path:
        return self.path / "map.csv"

    @property
    def map_ply(self) -> Path:
        return self.path / "map.ply"

    @property
    def map_npz(self) -> Path:
        """The map file: every landmark with its Gaussian and descriptor (`io/map_file.py`)."""
        return self.path / "map.npz"

    @property
    def timeline(self) -> Path:
        return self.path / "timeline.csv"

    @property
    def events(self) -> Path:
        return self.path / "events.csv"

    @property
    def result_mcap(self) -> Path:
        return self.path / "result.mcap"

    @property
    def observations(self) -> Path:
        """Every landmark observation the run used (`io/observations_file.py`; refine)."""
        return self.path / "observations.npz"

    @property
    def resolved_config(self) -> Path:
        return self.path / f"fuse{_CONFIG_SUFFIX}"

    def has_trajectories(self) -> bool:
        return self.path.is_dir() and any(self.path.glob("*.tum"))

    def vehicles(self) -> list[str]:
        """The vehicles with an estimated trajectory, sorted."""
        dr = f"_{DEADRECKONING}"
        return sorted(p.stem for p in self.path.glob("*.tum") if not p.stem.endswith(dr))

    def trajectories(self, vehicles: Sequence[str], *, deadreckoning: bool) -> dict[str, Path]:
        """The trajectory file of each vehicle; CvslamError naming the first one missing."""
        out = {v: self.trajectory(v, deadreckoning=deadreckoning) for v in vehicles}
        for path in out.values():
            if not path.exists():
                raise CvslamError(f"{path}: trajectory not found; run `cvslam fuse` first")
        return out

    def data_files(self) -> list[Path]:
        """The trajectories, tables and covariances (.tum, .csv, .npz) the folder holds."""
        return [p for p in self.path.iterdir() if p.suffix in (".tum", ".csv", ".npz")]


@dataclass(frozen=True)
class MosaicFolder:
    """The outputs of one `cvslam mosaic` run (docs/mosaic.md): per vehicle and for
    `MERGED_MOSAIC` an image, its world file, its GeoTIFF, and an overlay with its world
    file."""

    path: Path

    @property
    def name(self) -> str:
        return self.path.name

    def image(self, name: str) -> Path:
        return self.path / f"{name}.png"

    def world_file(self, name: str) -> Path:
        return self.path / f"{name}.pgw"

    def overlay(self, name: str) -> Path:
        return self.path / f"{name}_overlay.png"

    def overlay_world_file(self, name: str) -> Path:
        return self.path / f"{name}_overlay.pgw"

    def geotiff(self, name: str) -> Path:
        return self.path / f"{name}.tif"

    def pngs(self) -> list[Path]:
        """Every PNG in the folder (images and overlays), sorted; none without the folder."""
        return sorted(self.path.glob("*.png")) if self.path.is_dir() else []


@dataclass(frozen=True)
class EvalFolder:
    """The outputs of `cvslam eval` (docs/eval.md)."""

    path: Path

    @property
    def metrics_json(self) -> Path:
        return self.path / "metrics.json"

    @property
    def metrics_csv(self) -> Path:
        return self.path / "metrics.csv"

    @property
    def headline_csv(self) -> Path:
        return self.path / "headline.csv"

    @property
    def report_html(self) -> Path:
        return self.path / "report.html"

    def figure(self, name: str) -> Path:
        return self.path / "figures" / f"{name}.png"


@dataclass(frozen=True)
class RunLayout:
    """The names of a run directory `root` and where its inputs are found."""

    root: Path

    @property
    def run_file(self) -> Path:
        return self.root / RUN_FILE

    @property
    def lock_file(self) -> Path:
        return self.root / LOCK_FILE

    @property
    def log_file(self) -> Path:
        return self.root / LOG_FILE

    @property
    def features_dir(self) -> Path:
        return self.root / FEATURES

    def feature_file(self, vehicle: str) -> Path:
        return self.features_dir / f"{vehicle}.npz"

    def feature_stats(self, vehicle: str) -> Path:
        return self.features_dir / f"{vehicle}_stats.csv"

    @property
    def extract_config(self) -> Path:
        return self.features_dir / f"{EXTRACT_STAGE}{_CONFIG_SUFFIX}"

    def fuse(self, name: str = FUSE) -> FuseFolder:
        """A fuse folder by name (`fuse_name`, or `mosaic.fuse_dir` of the config)."""
        return FuseFolder(self.root / name)

    def fuse_folders(self) -> list[FuseFolder]:
        """Every fuse folder with trajectories (`fuse`, `fuse_ekf`, ...), sorted by name."""
        found = self.root.glob("fuse*") if self.root.is_dir() else []
        return sorted(
            (FuseFolder(p) for p in found if FuseFolder(p).has_trajectories()),
            key=lambda f: f.name,
        )

    def export_dir(self, source: str, frame: str) -> Path:
        """Where `cvslam export` writes the estimates of fuse folder `source` in `frame`."""
        return self.root / EXPORT / f"{source}_{frame}"

    def diverged_timeline(self, fuse: str) -> Path:
        """The timeline up to the divergence of a fuse run that wrote no outputs."""
        return self.root / f"{fuse}_diverged_timeline.csv"

    def mosaic(self, name: str = MOSAIC) -> MosaicFolder:
        return MosaicFolder(self.root / name)

    @property
    def eval(self) -> EvalFolder:
        return EvalFolder(self.root / EVAL)

    def feature_files(self, remedy: str) -> list[Path]:
        """The feature files (`features/<vehicle>.npz`), sorted; CvslamError ending with
        `remedy` (what to run first) when there are none."""
        fdir = self.features_dir
        files = sorted(fdir.glob("*.npz")) if fdir.is_dir() else []
        if not files:
            raise CvslamError(f"{fdir}: no feature files (<vehicle>.npz); {remedy}")
        return files

    def relative_inputs(self, records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
        """Input records (`path`, size, checksum) with each path relative to the run, as
        the files written into the run record them: the same run gives the same bytes
        wherever it is, and a moved run (with its logs) still finds them."""
        root = self.root.resolve()
        return [
            {**r, "path": os.path.relpath((self.root / r["path"]).resolve(), root)} for r in records
        ]

    def recorded_path(self, recorded: str) -> Path:
        """A path as `io/rundir.py` records it (relative to the run directory; absolute in
        older runs), usable from here."""
        p = Path(recorded)
        return p if p.is_absolute() else Path(os.path.normpath(self.root / p))

    def find_logs(self, metas: Sequence[dict[str, Any]]) -> list[Path]:
        """The logs the features were made from: the feature files' recorded inputs (their
        `metas`, from extract), else the logs beside `features/` (a simulator output
        directory)."""
        paths: list[Path] = []
        for meta in metas:
            for rec in meta.get("inputs", []):
                p = self.recorded_path(rec["path"])
                if p not in paths:
                    paths.append(p)
        if not paths:
            paths = sorted(self.root.glob(f"*{_LOG_SUFFIX}"))
        missing = [p for p in paths if not p.exists()]
        if missing:
            raise CvslamError(
                f"{missing[0]}: log recorded as the features' input not found; give the logs "
                "with --log"
            )
        return paths


@dataclass(frozen=True)
class SimLayout(RunLayout):
    """A simulator output directory: a run directory with the logs, the scenario and the
    truth (`truth/`) beside the features."""

    @property
    def scenario(self) -> Path:
        return self.root / "scenario.yaml"

    def log(self, vehicle: str) -> Path:
        return self.root / f"{vehicle}{_LOG_SUFFIX}"

    @property
    def truth_dir(self) -> Path:
        return self.root / TRUTH

    def true_trajectory(self, vehicle: str) -> Path:
        return self.truth_dir / f"{vehicle}.tum"

    def true_imu_biases(self, vehicle: str) -> Path:
        return self.truth_dir / f"{vehicle}_imu.npz"

    def true_depth(self, vehicle: str) -> Path:
        return self.truth_dir / f"{vehicle}_depth.npz"

    @property
    def world(self) -> Path:
        return self.truth_dir / "world.npz"

    @property
    def true_landmarks(self) -> Path:
        return self.truth_dir / "landmarks.csv"
