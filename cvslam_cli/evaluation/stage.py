"""`cvslam eval`: every estimate of a run directory against the ground truth: metrics,
figures like the paper's, one self-contained HTML report (docs/eval.md).

Estimates: each fuse folder present (`fuse` cooperative NH-infinity, `fuse_single`,
`fuse_ekf`, `fuse_ekf_single`, `fuse_refined` from `cvslam refine`) and the dead reckoning
(`fuse/<vehicle>_deadreckoning.tum`).
Truth: `--gt` files (TUM or KITTI, named `<vehicle>.*` or given as `VEHICLE=FILE`), else the
logs' ground-truth topic. Per estimate and vehicle (`metrics.py`, evo's definitions): ATE
(RMSE, mean, median, max; no alignment unless `eval.align`), RPE over travelled distances
(as % of the distance), final drift (m and % of the path), NEES of the position where the
fuse run wrote pose covariances (mean, and the fraction inside the chi-square band).

Outputs, in `<run>/eval/` (written as a whole folder, atomically: `io/atomic.py`): `metrics.json`,
`metrics.csv` (one row per estimate and vehicle), `headline.csv`, `figures/*.png`,
`report.html`.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from tqdm import tqdm

from cvslam_cli import __version__
from cvslam_cli.config import Config, EvalConfig, LogsConfig, dump_config
from cvslam_cli.errors import CvslamError
from cvslam_cli.evaluation import figures as figs
from cvslam_cli.evaluation import metrics as mtr
from cvslam_cli.evaluation.report import FigureEntry, render_report
from cvslam_cli.geometry.nav_frames import table_to_nav
from cvslam_cli.io.atomic import atomic_dir, check_writable, write_bytes_atomic, write_text_atomic
from cvslam_cli.io.features_file import feature_frame_index
from cvslam_cli.io.fuse_files import load_pose_covariances, read_map_csv
from cvslam_cli.io.logs import (
    LogSet,
    all_log_paths,
    ground_truth_tables,
    open_logs,
    with_run_bindings,
)
from cvslam_cli.io.mosaic_files import read_world_file
from cvslam_cli.io.run_layout import (
    DEADRECKONING,
    EVAL,
    EXTRACT_STAGE,
    FUSE,
    FUSE_EKF,
    FUSE_EKF_SINGLE,
    FUSE_REFINED,
    FUSE_SINGLE,
    MERGED_MOSAIC,
    MOSAIC,
    EvalFolder,
    FuseFolder,
    MosaicFolder,
    RunLayout,
    refined_name,
)
from cvslam_cli.io.rundir import RunDir, input_record
from cvslam_cli.io.trajectory import read_trajectory_file, read_tum
from cvslam_cli.records.poses import PoseTable

log = logging.getLogger("cvslam")

# fuse folder -> label, in the report's order
RUN_LABELS = {
    FUSE: "cooperative NH-inf",
    FUSE_SINGLE: "single NH-inf",
    FUSE_EKF: "cooperative EKF",
    FUSE_EKF_SINGLE: "single EKF",
    # `cvslam refine` of each (the batch solution over the same observations)
    FUSE_REFINED: "refined",
    refined_name(FUSE_EKF): "refined EKF",
    refined_name(FUSE_SINGLE): "refined single",
    refined_name(FUSE_EKF_SINGLE): "refined single EKF",
}
DR_LABEL = "dead reckoning"
# the NEES figure starts each line at the first pose whose NEES a consistent filter exceeds
# with probability 1 - this (the chi-square lower quantile)
NEES_UNINFORMATIVE_P = 0.001


@dataclass(frozen=True)
class EvalSummary:
    run_dir: Path
    out_dir: Path
    skipped: bool
    headline: pd.DataFrame
    metrics: pd.DataFrame
    wall_s: float = float("nan")


@dataclass(frozen=True, eq=False)
class _Estimate:
    run: str  # fuse folder, or DEADRECKONING
    label: str
    vehicle: str
    table: PoseTable
    cov: np.ndarray | None  # (K, 6, 6) at table's stamps, or None
    path: Path


# --------------------------------------------------------------------------- inputs


def _fuse_runs(layout: RunLayout) -> list[FuseFolder]:
    """The fuse folders with trajectories, in the report's order."""
    runs = [f for f in map(layout.fuse, RUN_LABELS) if f.has_trajectories()]
    if not runs:
        raise CvslamError(
            f"{layout.root}: no fuse output (fuse*/<vehicle>.tum); run `cvslam fuse` first"
        )
    return runs


def _gt_from_files(
    specs: Sequence[str], vehicles: Sequence[str], logs_cfg: LogsConfig
) -> tuple[dict[str, PoseTable], list[Path]]:
    """(truth per vehicle, the files) from `--gt` specs: FILE named <vehicle>.* or
    VEHICLE=FILE; TUM, KITTI or EuRoC CSV, in the vehicle's `ground_truth_frame`."""
    out: dict[str, PoseTable] = {}
    files: list[Path] = []
    for spec in specs:
        vehicle, sep, file = spec.partition("=")
        path = Path(file if sep else spec)
        if not sep:
            vehicle = path.stem
        if vehicle not in vehicles:
            raise CvslamError(
                f"--gt {spec}: no estimate of vehicle {vehicle!r} in the run (vehicles: "
                f"{', '.join(vehicles)}); name the file <vehicle>.tum or give VEHICLE=FILE"
            )
        if not path.is_file():
            raise CvslamError(f"--gt {spec}: {path} not found")
        vcfg = logs_cfg.vehicles.get(vehicle, logs_cfg.vehicle_defaults)
        out[vehicle] = table_to_nav(read_trajectory_file(path), vcfg.ground_truth_frame)
        files.append(path)
    return out, files


def _logs(cfg: Config, run_dir: Path, log_paths: Sequence[Path]) -> tuple[LogSet, list[Path]]:
    _, metas = feature_frame_index(run_dir)
    cfg = dataclasses.replace(cfg, logs=with_run_bindings(cfg.logs, run_dir))
    logs_used = all_log_paths(list(log_paths) or RunLayout(run_dir).find_logs(metas), cfg.logs)
    return open_logs(logs_used, cfg.logs), logs_used


def _with_truth(logs: LogSet, vehicles: Sequence[str]) -> list[str]:
    return [
        v for v in vehicles if v in logs.vehicles and "ground_truth" in logs.vehicles[v].present
    ]


def has_ground_truth(cfg: Config, run_dir: Path) -> bool:
    """Whether the logs of the run hold ground truth for some vehicle."""
    logs, _ = _logs(cfg, run_dir, ())
    return bool(_with_truth(logs, list(logs.vehicles)))


def _ground_truth(
    cfg: Config, run_dir: Path, gt: Sequence[str], vehicles: list[str], log_paths: Sequence[Path]
) -> tuple[dict[str, PoseTable], list[Path], str]:
    """(truth per vehicle, files it came from, a description)."""
    if gt:
        truth, files = _gt_from_files(gt, vehicles, cfg.logs)
        missing = [v for v in vehicles if v not in truth]
        if missing:
            log.warning("eval: no ground truth given for %s: not evaluated", ", ".join(missing))
        return truth, files, "files " + ", ".join(map(str, files))
    logs, logs_used = _logs(cfg, run_dir, log_paths)
    have = _with_truth(logs, vehicles)
    if not have:
        raise CvslamError(
            f"{logs.names}: no ground-truth topic for any vehicle; give the truth with "
            "--gt FILE (TUM or KITTI, named <vehicle>.tum, or VEHICLE=FILE)"
        )
    return ground_truth_tables(logs, have), logs_used, "the logs' ground-truth topic"


def _estimates(runs: list[FuseFolder], vehicles: list[str]) -> list[_Estimate]:
    """Each run's estimate of each vehicle (with its pose covariances where they match its
    stamps), then the dead reckoning of the first run."""
    out: list[_Estimate] = []
    for r in runs:
        for v in vehicles:
            path = r.trajectory(v)
            if not path.exists():
                continue
            cov_path = r.pose_covariances(v)
            table = read_tum(path)
            cov = None
            if cov_path.exists():
                st, c = load_pose_covariances(cov_path)
                if len(st) == len(table) and np.array_equal(st, table.stamps_ns):
                    cov = c
            out.append(_Estimate(r.name, RUN_LABELS[r.name], v, table, cov, path))
    for v in vehicles:
        path = runs[0].trajectory(v, deadreckoning=True)
        if path.exists():
            out.append(_Estimate(DEADRECKONING, DR_LABEL, v, read_tum(path), None, path))
    return out


# --------------------------------------------------------------------------- metrics


# the position NEES of one estimate over time: (stamps_ns, NEES, degrees of freedom)
_Nees = tuple[np.ndarray, np.ndarray, int]


def _metrics(
    e: _Estimate, truth: PoseTable, cfg: EvalConfig
) -> tuple[dict[str, Any], _Nees | None]:
    """One row of metrics.csv: ATE statistics, RPE per distance (as % of the distance, KITTI
    style, pairs chosen on the true path), final drift, position NEES; and the NEES over
    time (estimate stamps_ns, NEES) where the estimate has covariances."""
    max_diff = int(cfg.max_time_diff_ms * 1e6)
    a = mtr.ate(truth, e.table, align=cfg.align, max_diff_ns=max_diff)
    length = mtr.path_length_m(truth.p_nav_m[a.ref_idx])
    row: dict[str, Any] = {
        "run": e.run,
        "estimate": e.label,
        "vehicle": e.vehicle,
        "poses": len(a.errors_m),
        "distance_m": length,
        "ate_rmse_m": a.rmse,
        "ate_mean_m": a.mean,
        "ate_median_m": a.median,
        "ate_max_m": a.max,
    }
    try:  # evo_rpe's default: consecutive poses (delta 1 frame)
        r1 = mtr.rpe(truth, e.table, 1, "frames", align=cfg.align, max_diff_ns=max_diff)
        row["rpe_frame_rmse_m"], row["rpe_frame_mean_m"] = r1.rmse, r1.mean
    except ValueError:
        row["rpe_frame_rmse_m"] = row["rpe_frame_mean_m"] = float("nan")
    row["final_error_m"], row["final_drift_pct"] = mtr.final_drift(
        truth, e.table, cfg.align, max_diff_ns=max_diff
    )
    if cfg.rpe_delta_m:
        drift = mtr.rpe_per_distance(
            truth, e.table, [float(d) for d in cfg.rpe_delta_m], align=cfg.align,
            max_diff_ns=max_diff,
        )  # fmt: skip
    else:
        drift = mtr.rpe_per_distance(
            truth, e.table, fractions=(0.10, 0.25), align=cfg.align, max_diff_ns=max_diff
        )
    for k, d in enumerate(drift.rows):
        name = f"{d.delta_m:.3g}m" if cfg.rpe_delta_m else ("10pct", "25pct")[k]
        row[f"rpe_{name}_delta_m"] = d.delta_m
        row[f"rpe_{name}_drift_pct"] = d.mean_pct
    row["rpe_drift_pct"] = drift.average_pct
    if e.cov is None:
        return row, None
    cov = e.cov[a.est_idx, :3, :3]
    # the axes the filter estimates: a ground robot (3-DOF) has no height uncertainty, and
    # its NEES is that of the horizontal position (2 dof)
    axes = [k for k in range(3) if np.all(cov[:, k, k] > 0)]
    nees = mtr.nees_position(
        truth.p_nav_m[a.ref_idx][:, axes],
        e.table.p_nav_m[a.est_idx][:, axes],
        cov[:, axes][:, :, axes],
    )
    lo, hi = _nees_band(cfg, len(axes))
    row["nees_mean"] = float(np.mean(nees))
    row["nees_in_band"] = float(np.mean((nees >= lo) & (nees <= hi)))
    row["nees_dof"] = len(axes)
    return row, (e.table.stamps_ns[a.est_idx], nees, len(axes))


def _nees_band(cfg: EvalConfig, dof: int) -> tuple[float, float]:
    """The band one run's position NEES (`dof` axes) lies in with the configured
    probability."""
    return mtr.nees_chi2_band(dof, 1, cfg.nees_band_probability)


def _all_metrics(
    estimates: list[_Estimate],
    truth: dict[str, PoseTable],
    truth_source: str,
    cfg: EvalConfig,
    tick: Callable[[], object] = lambda: None,
) -> tuple[list[dict[str, Any]], dict[tuple[str, str], _Nees]]:
    """(one metrics row per estimate, the NEES over time per (run, vehicle) that has one);
    `tick()` after each estimate (the progress bar)."""
    rows = []
    nees_of = {}
    for e in estimates:
        try:
            row, nees_series = _metrics(e, truth[e.vehicle], cfg)
        except ValueError as exc:  # no matching stamps, degenerate alignment
            raise CvslamError(
                f"{e.path}: cannot be compared with the ground truth of {e.vehicle} "
                f"({truth_source}): {exc}"
            ) from None
        rows.append(row)
        if nees_series is not None:
            nees_of[(e.run, e.vehicle)] = nees_series
        log.debug(
            "eval: %s, %s: %d poses matched (eval.max_time_diff_ms %g), ATE RMSE %.3f m",
            e.label,
            e.vehicle,
            row["poses"],
            cfg.max_time_diff_ms,
            row["ate_rmse_m"],
        )
        tick()
    return rows, nees_of


def _headline(metrics: pd.DataFrame) -> pd.DataFrame:
    """ATE RMSE per vehicle (rows) and estimate (columns, in report order)."""
    order = [*RUN_LABELS.values(), DR_LABEL]
    table = metrics.pivot_table(index="vehicle", columns="estimate", values="ate_rmse_m")
    table = table[[c for c in order if c in table.columns]]
    table.columns.name = None
    table.index.name = "ATE RMSE [m]"
    return table


# --------------------------------------------------------------------------- figures


def _series(e: _Estimate, t0_ns: int, label: str | None = None) -> figs.Series:
    sigma = None
    if e.cov is not None:
        sigma = np.sqrt(np.maximum(np.diagonal(e.cov[:, :3, :3], axis1=1, axis2=2), 0.0))
    return figs.Series(
        e.vehicle,
        label or e.label,
        (e.table.stamps_ns - t0_ns) * 1e-9,
        e.table.p_nav_m,
        sigma,
    )


def _truth_series(vehicle: str, truth: PoseTable, t0_ns: int) -> figs.Series:
    return figs.Series(vehicle, "ground truth", (truth.stamps_ns - t0_ns) * 1e-9, truth.p_nav_m)


# (figure, file name, title, caption), in the report's order
_Figure = tuple[Figure, str, str, str]
_Estimates = dict[tuple[str, str], _Estimate]  # by (run, vehicle)


def _headline_figure(headline: pd.DataFrame, cfg: EvalConfig) -> Iterator[_Figure]:
    yield (
        figs.headline_bars(headline),
        "headline",
        "Position error (ATE RMSE) per vehicle and estimate",
        "Root mean square position error against the ground truth, no alignment unless "
        f"configured (eval.align = {cfg.align}).",
    )


def _position_figures(
    by: _Estimates, truth: dict[str, PoseTable], main_run: str | None, t0_ns: int
) -> Iterator[_Figure]:
    for v in sorted(truth):
        est = by.get((main_run, v)) if main_run else None
        if est is None:
            continue
        dr = by.get((DEADRECKONING, v))
        yield (
            figs.position_components(
                _truth_series(v, truth[v], t0_ns),
                _series(est, t0_ns),
                _series(dr, t0_ns) if dr else None,
            ),
            f"position_{v}",
            f"{v}: position over time (paper Fig. 10)",
            f"North, east and height of {v}: ground truth, dead reckoning and the "
            f"{est.label} estimate with its 3-sigma band.",
        )


def _map_and_timeline_figures(
    fuse: FuseFolder,
    by: _Estimates,
    truth: dict[str, PoseTable],
    main_run: str | None,
    t0_ns: int,
    fleet: list[str],
) -> Iterator[_Figure]:
    """The map from above (with the main run), the landmark uncertainty and the feature
    counts over time from `fuse`'s timeline and events (for a lone vehicle, without what
    only a team has: other vehicles' landmarks, type 2)."""
    alone = len(fleet) == 1
    vehicles = sorted(truth)
    if main_run and fuse.map_csv.exists():
        table = read_map_csv(fuse.map_csv)
        tracks = [_series(by[(main_run, v)], t0_ns) for v in vehicles if (main_run, v) in by]
        truths = [_truth_series(v, truth[v], t0_ns) for v in vehicles]
        yield (
            figs.top_view(tracks, truths, table.p_nav_m[:, :2], list(table.observers)),
            "top_view",
            "Trajectories and map from above (paper Fig. 11)",
            "Estimated (solid) and true (dashed) paths of every vehicle and the landmark map, "
            "coloured by the vehicle that observed each landmark.",
        )
    if fuse.timeline.exists() and fuse.events.exists():
        timeline = pd.read_csv(fuse.timeline)
        events = pd.read_csv(fuse.events)
        yield (
            figs.landmark_uncertainty(timeline, events, t0_ns),
            "landmark_uncertainty",
            "Landmark uncertainty over time (paper Fig. 12)",
            "RMS standard deviation of the landmarks updated in each frame; loop closures "
            + ("(lines)." if alone else "(lines) and re-observations of other vehicles' "
               "landmarks (type 2, shaded)."),
        )  # fmt: skip
        yield (
            figs.feature_counts(
                timeline, t0_ns, types=("type1", "type3") if alone else ("type1", "type2", "type3")
            ),
            "feature_counts",
            "Features per frame by type",
            "Type 1: re-observations of the vehicle's own landmarks; "
            + ("" if alone else "type 2: landmarks mapped by another vehicle; ")
            + "type 3: new landmarks.",
        )


def _comparison_figures(
    by: _Estimates, truth: dict[str, PoseTable], t0_ns: int, fleet: list[str]
) -> Iterator[_Figure]:
    """Position errors of runs compared, where both runs of a pair were made; single vs
    cooperative only for a team (a lone vehicle's two runs are the same filter)."""
    pairs = [
        (FUSE_EKF, FUSE, "EKF vs NH-infinity", "filters"),
        (FUSE, FUSE_REFINED, "filter vs refined (batch)", "refined"),
    ]
    if len(fleet) > 1:
        pairs.insert(0, (FUSE_SINGLE, FUSE, "single vs cooperative (paper Fig. 13/17)", "coop"))
    for v in sorted(truth):
        for a, b, what, tag in pairs:
            ests = [by[(r, v)] for r in (a, b, DEADRECKONING) if (r, v) in by]
            if (a, v) in by and (b, v) in by:
                yield (
                    figs.error_over_time(
                        _truth_series(v, truth[v], t0_ns),
                        [_series(e, t0_ns) for e in ests],
                        f"{v}: {what}",
                    ),
                    f"error_{tag}_{v}",
                    f"{v}: position error, {what}",
                    "Position error against the ground truth over time; RMSE in the legend.",
                )


def _nees_figure(
    nees_of: dict[tuple[str, str], _Nees],
    vehicles: list[str],
    main_run: str | None,
    t0_ns: int,
    cfg: EvalConfig,
) -> Iterator[_Figure]:
    main_nees = {v: nees_of[(main_run, v)] for v in vehicles if (main_run, v) in nees_of}
    nees_t = {v: (st - t0_ns) * 1e-9 for v, (st, _, _) in main_nees.items()}
    nees = {v: n for v, (_, n, _) in main_nees.items()}
    if nees:
        dof = max(d for _, _, d in main_nees.values())  # 2 for a team of ground robots
        # a consistent filter's NEES is below this 0.1 % of the time: values below it
        # before the first one above are the start at the truth, not information
        informative = mtr.nees_chi2_band(dof, 1, 1.0 - 2 * NEES_UNINFORMATIVE_P)[0]
        yield (
            figs.nees_over_time(
                nees_t, nees, _nees_band(cfg, dof), dof, informative_from=informative
            ),
            "nees",
            "Position NEES over time",
            "Normalised estimation error squared of each vehicle's position "
            f"({RUN_LABELS[main_run]}) and the {100 * cfg.nees_band_probability:.0f} % "
            f"chi-square band ({dof} dof): a consistent filter stays inside it. Each line "
            f"starts at the vehicle's first pose whose NEES reaches {informative:.2g} (the "
            f"{100 * NEES_UNINFORMATIVE_P:.1f} % quantile of the chi-square distribution): "
            "the filter starts at the true pose with a small covariance, so its first NEES "
            "values are near 0 and say nothing about consistency (the legend says how many "
            "poses that leaves out; the tables count every pose).",
        )


def _mosaic_figure(mosaic: MosaicFolder, fleet: list[str]) -> Iterator[_Figure]:
    """The fused mosaics of every vehicle and the merged one (a lone vehicle's only: the
    merged one is the same), at most 1200 px each, with scale bars from their world files."""
    if not mosaic.path.is_dir():
        return
    images, gsd_m = {}, {}
    for name in [*fleet, MERGED_MOSAIC] if len(fleet) > 1 else fleet:
        p = mosaic.image(name)
        if p.exists():
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            width = img.shape[1]
            scale = 1200.0 / max(img.shape[:2])
            if scale < 1:
                img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            images[name] = img
            if mosaic.world_file(name).exists():  # metres per pixel: the length of (A, D)
                a, d = read_world_file(mosaic.world_file(name))[:2]
                gsd_m[name] = float(np.hypot(a, d)) * width / img.shape[1]
    if images:
        team = len(fleet) > 1
        yield (
            figs.mosaics(images, merged=MERGED_MOSAIC, gsd_m=gsd_m),
            "mosaics",
            "Ground mosaics (paper Figs. 19-21)",
            (
                "Each vehicle's mosaic from its fused poses and the merged one: the team covers "
                "more ground than any one vehicle"
                if team
                else "The vehicle's mosaic from its fused poses"
            )
            + "; north up, scale bar in metres (docs/mosaic.md).",
        )


def _figures(
    layout: RunLayout,
    out: EvalFolder,
    estimates: list[_Estimate],
    truth: dict[str, PoseTable],
    headline: pd.DataFrame,
    nees_of: dict[tuple[str, str], _Nees],
    cfg: EvalConfig,
    tick: Callable[[], object] = lambda: None,
) -> list[FigureEntry]:
    """Every figure of the report, each written as soon as it is made (one in memory);
    `tick()` after each (the progress bar)."""
    t0_ns = min(int(t.stamps_ns[0]) for t in truth.values())
    by = {(e.run, e.vehicle): e for e in estimates}
    main_run = next((r for r in RUN_LABELS if any(k[0] == r for k in by)), None)
    vehicles = sorted(truth)
    main = layout.fuse(main_run or FUSE)
    fleet = main.vehicles() if main.has_trajectories() else vehicles  # the team, truth or not
    made = itertools.chain(
        _headline_figure(headline, cfg),
        _position_figures(by, truth, main_run, t0_ns),
        _map_and_timeline_figures(main, by, truth, main_run, t0_ns, fleet),
        _comparison_figures(by, truth, t0_ns, fleet),
        _nees_figure(nees_of, vehicles, main_run, t0_ns, cfg),
        _mosaic_figure(layout.mosaic(), fleet),
    )
    entries: list[FigureEntry] = []
    for fig, name, title, caption in made:
        path = out.figure(name)
        write_bytes_atomic(path, figs.png_bytes(fig))
        entries.append(FigureEntry(path, title, caption))
        tick()
    return entries


# --------------------------------------------------------------------------- outputs


def _provenance(
    rd: RunDir, truth_source: str, truth_files: list[Path], runs: list[FuseFolder], align: str
) -> dict[str, str]:
    """Where the report's data came from: the truth's files, the stages that made the
    estimates and mosaics."""
    inputs = [input_record(p, rd.path) for p in truth_files]  # relative to the run
    provenance = {  # paths relative to the run: the report is the same wherever the run is
        "ground truth": truth_source,
        "cvslam version": __version__,
        "evaluated": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "alignment": align,
        **{f"input {r['path']}": f"sha256 {r['sha256'][:16]}..., {r['size']} bytes"
           for r in inputs},
    }  # fmt: skip
    stages = rd.load().get("stages", {})
    for name in (*(r.name for r in runs), MOSAIC, EXTRACT_STAGE):
        if name in stages:
            st = stages[name]
            provenance[f"stage {name}"] = (
                f"{st.get('finished', '?')}, config {st.get('config_digest', '?')}"
            )
    return provenance


def _metrics_json(
    headline: pd.DataFrame, rows: list[dict[str, Any]], truth_source: str, align: str
) -> dict[str, Any]:
    return {
        "cvslam_version": __version__,
        "align": align,
        "ground_truth": truth_source,
        "headline_ate_rmse_m": {
            v: {k: _num(x) for k, x in row.items()} for v, row in headline.iterrows()
        },
        "estimates": [{k: _num(x) for k, x in r.items()} for r in rows],
    }


def _report_html(
    cfg: Config,
    run_dir: Path,
    n_vehicles: int,
    estimates: list[_Estimate],
    headline: pd.DataFrame,
    metrics: pd.DataFrame,
    entries: list[FigureEntry],
    provenance: dict[str, str],
) -> str:
    dataset = cfg.run.dataset or run_dir.resolve().name
    return render_report(
        title=f"cvslam evaluation: {run_dir.name}",
        subtitle=f"dataset {dataset}; {n_vehicles} vehicle(s), estimates: "
        + ", ".join(dict.fromkeys(e.label for e in estimates)),
        headline=headline,
        headline_note="ATE RMSE in metres against the ground truth "
        f"({'no alignment' if cfg.eval.align == 'none' else cfg.eval.align + ' alignment'}).",
        figures=entries,
        # one row per (vehicle, estimate); the run folder, dataset and run directory are
        # the same for every row of the report (and in metrics.csv)
        metrics=metrics.drop(columns=["run", "dataset", "run_dir"])
        .astype({c: "Int64" for c in ("nees_dof",) if c in metrics})  # a count, or none
        .set_index(["vehicle", "estimate"]),
        config_yaml=dump_config(cfg),
        provenance=provenance,
    )


def _record_summary(metrics_json: dict[str, Any], figures: int) -> dict[str, Any]:
    """The eval run's summary in run.yaml."""
    return {
        "headline_ate_rmse_m": {
            v: {k: None if x is None else round(x, 4) for k, x in row.items()}
            for v, row in metrics_json["headline_ate_rmse_m"].items()
        },
        "figures": figures,
    }


# --------------------------------------------------------------------------- stage


def run(
    cfg: Config,
    run_dir: Path,
    *,
    gt: Sequence[str] = (),
    log_paths: Sequence[Path] = (),
    force: bool = False,
    progress: bool = False,
) -> EvalSummary:
    """Evaluate every estimate of `run_dir`; `progress`: a progress bar (on a terminal)
    over the estimates, then the figures."""
    t_start = time.perf_counter()
    layout = RunLayout(run_dir)
    rd = RunDir(run_dir)
    runs = _fuse_runs(layout)
    vehicles = runs[0].vehicles()
    truth, truth_files, truth_source = _ground_truth(cfg, run_dir, gt, vehicles, log_paths)
    est_files = sorted(p for r in runs for p in r.data_files())
    out = layout.eval
    outputs = [out.metrics_json, out.metrics_csv, out.headline_csv, out.report_html]
    inputs = [*truth_files, *est_files, *layout.mosaic().pngs()]
    plan = rd.plan(EVAL, cfg, ("eval", "run.dataset"), inputs, outputs, force)
    if plan.action == "skip":
        log.info("eval: %s is up to date (same config and inputs); --force to redo it", out.path)
        old = pd.read_csv(out.headline_csv, index_col=0)
        return EvalSummary(run_dir, out.path, True, old, pd.read_csv(out.metrics_csv))
    check_writable(outputs)  # before the work: a read-only folder, a name too long
    estimates = [e for e in _estimates(runs, vehicles) if e.vehicle in truth]
    log.debug(
        "eval: %d estimate(s) of %s against %s, alignment %s (eval.align)",
        len(estimates),
        ", ".join(sorted(truth)),
        truth_source,
        cfg.eval.align,
    )
    with _bar(progress, "eval metrics", "estimate", len(estimates)) as bar:
        rows, nees_of = _all_metrics(estimates, truth, truth_source, cfg.eval, bar.update)
    # which run and dataset each row is of, for tables across runs (`cvslam summary`)
    dataset = cfg.run.dataset or run_dir.resolve().name
    rows = [{"dataset": dataset, "run_dir": run_dir.resolve().name, **r} for r in rows]
    metrics = pd.DataFrame(rows)
    headline = _headline(metrics)

    with atomic_dir(out.path) as tmp:
        written = EvalFolder(tmp)
        with _bar(progress, "eval figures", "figure") as bar:
            entries = _figures(
                layout, written, estimates, truth, headline, nees_of, cfg.eval, bar.update
            )
        metrics.to_csv(written.metrics_csv, index=False)  # full precision (repr)
        headline.to_csv(written.headline_csv)
        provenance = _provenance(rd, truth_source, truth_files, runs, cfg.eval.align)
        metrics_json = _metrics_json(headline, rows, truth_source, cfg.eval.align)
        write_text_atomic(written.metrics_json, json.dumps(metrics_json, indent=2) + "\n")
        html = _report_html(
            cfg, run_dir, len(truth), estimates, headline, metrics, entries, provenance
        )
        write_text_atomic(written.report_html, html)
    wall = time.perf_counter() - t_start
    rd.record(EVAL, plan, outputs, _record_summary(metrics_json, len(entries)), wall)
    return EvalSummary(run_dir, out.path, False, headline, metrics, wall)


def _bar(progress: bool, desc: str, unit: str, total: int | None = None) -> tqdm:
    """A progress bar like the other stages': on a terminal, when `progress`."""
    return tqdm(total=total, desc=desc, unit=unit, disable=None if progress else True, leave=False)


def _num(x: Any) -> Any:
    if isinstance(x, (float, np.floating)):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    return x


def headline_text(headline: pd.DataFrame) -> str:
    """The headline table as aligned text for the terminal."""
    return headline.to_string(float_format=lambda x: f"{x:.2f}", na_rep="-")
