"""`cvslam eval`: every estimate of a run directory against the ground truth: metrics,
figures like the paper's, one self-contained HTML report (docs/eval.md).

Estimates: each fuse folder present (`fuse` cooperative NH-infinity, `fuse_single`,
`fuse_ekf`, `fuse_ekf_single`) and the dead reckoning (`fuse/<vehicle>_deadreckoning.tum`).
Truth: `--gt` files (TUM or KITTI, named `<vehicle>.*` or given as `VEHICLE=FILE`), else the
logs' ground-truth topic. Per estimate and vehicle (`metrics.py`, evo's definitions): ATE
(RMSE, mean, median, max; no alignment unless `eval.align`), RPE over travelled distances
(as % of the distance), final drift (m and % of the path), NEES of the position where the
fuse run wrote pose covariances (mean, and the fraction inside the chi-square band).

Outputs, in `<run>/eval.partial/` renamed to `<run>/eval/` when complete: `metrics.json`,
`metrics.csv` (one row per estimate and vehicle), `headline.csv`, `figures/*.png`,
`report.html`.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from cvslam_cli import __version__
from cvslam_cli.config import Config, EvalConfig, dump_config
from cvslam_cli.errors import CvslamError
from cvslam_cli.estimation.stage import find_logs
from cvslam_cli.evaluation import figures as figs
from cvslam_cli.evaluation import metrics as mtr
from cvslam_cli.evaluation.report import FigureEntry, render_report
from cvslam_cli.io.features_file import feature_frame_index
from cvslam_cli.io.fuse_files import load_pose_covariances, read_map_csv
from cvslam_cli.io.logs import LogSet, ground_truth_tables
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.rundir import RunDir, input_record, write_text_atomic
from cvslam_cli.io.trajectory import read_kitti, read_tum
from cvslam_cli.records.poses import PoseTable

log = logging.getLogger("cvslam")

# fuse folder -> label, in the report's order
RUN_LABELS = {
    "fuse": "cooperative NH-inf",
    "fuse_single": "single NH-inf",
    "fuse_ekf": "cooperative EKF",
    "fuse_ekf_single": "single EKF",
}
DR_LABEL = "dead reckoning"
MOSAIC_DIR = "mosaic"


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
    run: str  # fuse folder, or "deadreckoning"
    label: str
    vehicle: str
    table: PoseTable
    cov: np.ndarray | None  # (K, 6, 6) at table's stamps, or None
    path: Path


# --------------------------------------------------------------------------- inputs


def _runs_present(run_dir: Path) -> list[str]:
    return [r for r in RUN_LABELS if (run_dir / r).is_dir() and any((run_dir / r).glob("*.tum"))]


def _vehicles_of(folder: Path) -> list[str]:
    return sorted(p.stem for p in folder.glob("*.tum") if not p.stem.endswith("_deadreckoning"))


def _read_trajectory(path: Path) -> PoseTable:
    """TUM (8 numbers per line) or KITTI (12) by content."""
    first = next(
        (ln.split() for ln in path.read_text(encoding="utf-8").splitlines() if ln.strip()
         and not ln.lstrip().startswith("#")),
        [],
    )  # fmt: skip
    if len(first) == 12:
        return read_kitti(path)
    return read_tum(path)


def _gt_from_files(
    specs: Sequence[str], vehicles: Sequence[str]
) -> tuple[dict[str, PoseTable], list[Path]]:
    """(truth per vehicle, the files) from `--gt` specs: FILE named <vehicle>.* or
    VEHICLE=FILE."""
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
        out[vehicle] = _read_trajectory(path)
        files.append(path)
    return out, files


def _logs(cfg: Config, run_dir: Path, log_paths: Sequence[Path]) -> tuple[LogSet, list[Path]]:
    _, metas = feature_frame_index(run_dir)
    logs_used = list(log_paths) or find_logs(run_dir, metas)
    return LogSet([McapLogSource(p) for p in logs_used], cfg.logs), logs_used


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
        truth, files = _gt_from_files(gt, vehicles)
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


def _estimates(run_dir: Path, runs: list[str], vehicles: list[str]) -> list[_Estimate]:
    out: list[_Estimate] = []
    for r in runs:
        for v in vehicles:
            path = run_dir / r / f"{v}.tum"
            if not path.exists():
                continue
            cov_path = run_dir / r / f"{v}_pose_cov.npz"
            table = read_tum(path)
            cov = None
            if cov_path.exists():
                st, c = load_pose_covariances(cov_path)
                if len(st) == len(table) and np.array_equal(st, table.stamps_ns):
                    cov = c
            out.append(_Estimate(r, RUN_LABELS[r], v, table, cov, path))
    dr_dir = run_dir / runs[0]
    for v in vehicles:
        path = dr_dir / f"{v}_deadreckoning.tum"
        if path.exists():
            out.append(_Estimate("deadreckoning", DR_LABEL, v, read_tum(path), None, path))
    return out


# --------------------------------------------------------------------------- metrics


def _metrics(
    e: _Estimate, truth: PoseTable, cfg: EvalConfig
) -> tuple[dict[str, Any], tuple[np.ndarray, np.ndarray] | None]:
    """One row of metrics.csv: ATE statistics, RPE per distance (as % of the distance, KITTI
    style, pairs chosen on the true path), final drift, position NEES; and the NEES over
    time (estimate stamps_ns, NEES) where the estimate has covariances."""
    max_diff = int(cfg.max_time_diff_ms * 1e6)
    a = mtr.ate(truth, e.table, align=cfg.align, max_diff_ns=max_diff)
    length = mtr.path_length_m(truth.p_m[a.ref_idx])
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
    nees = mtr.nees_position(truth.p_m[a.ref_idx], e.table.p_m[a.est_idx], e.cov[a.est_idx, :3, :3])
    lo, hi = _nees_band(cfg)
    row["nees_mean"] = float(np.mean(nees))
    row["nees_in_band"] = float(np.mean((nees >= lo) & (nees <= hi)))
    return row, (e.table.stamps_ns[a.est_idx], nees)


def _nees_band(cfg: EvalConfig) -> tuple[float, float]:
    """The band one run's position NEES (3 dof) lies in with the configured probability."""
    return mtr.nees_chi2_band(3, 1, cfg.nees_band_probability)


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
        e.table.p_m,
        sigma,
    )


def _truth_series(vehicle: str, truth: PoseTable, t0_ns: int) -> figs.Series:
    return figs.Series(vehicle, "ground truth", (truth.stamps_ns - t0_ns) * 1e-9, truth.p_m)


def _figures(
    run_dir: Path,
    out: Path,
    estimates: list[_Estimate],
    truth: dict[str, PoseTable],
    headline: pd.DataFrame,
    nees_of: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]],
    cfg: EvalConfig,
) -> list[FigureEntry]:
    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    entries: list[FigureEntry] = []
    t0 = min(int(t.stamps_ns[0]) for t in truth.values())
    by = {(e.run, e.vehicle): e for e in estimates}
    main_run = next((r for r in RUN_LABELS if any(k[0] == r for k in by)), None)
    vehicles = sorted(truth)

    def add(fig: Any, name: str, title: str, caption: str) -> None:
        path = figdir / f"{name}.png"
        figs.save_png(fig, path)
        entries.append(FigureEntry(path, title, caption))

    add(
        figs.headline_bars(headline),
        "headline",
        "Position error (ATE RMSE) per vehicle and estimate",
        "Root mean square position error against the ground truth, no alignment unless "
        f"configured (eval.align = {cfg.align}).",
    )
    for v in vehicles:
        est = by.get((main_run, v)) if main_run else None
        if est is None:
            continue
        dr = by.get(("deadreckoning", v))
        add(
            figs.position_components(
                _truth_series(v, truth[v], t0), _series(est, t0), _series(dr, t0) if dr else None
            ),
            f"position_{v}",
            f"{v}: position over time (paper Fig. 10)",
            f"North, east and height of {v}: ground truth, dead reckoning and the "
            f"{est.label} estimate with its 3-sigma band.",
        )
    tl_path = run_dir / (main_run or "fuse") / "timeline.csv"
    ev_path = run_dir / (main_run or "fuse") / "events.csv"
    map_path = run_dir / (main_run or "fuse") / "map.csv"
    if main_run and map_path.exists():
        table = read_map_csv(map_path)
        tracks = [_series(by[(main_run, v)], t0) for v in vehicles if (main_run, v) in by]
        truths = [_truth_series(v, truth[v], t0) for v in vehicles]
        add(
            figs.top_view(tracks, truths, table.p_nav_m[:, :2], list(table.observers)),
            "top_view",
            "Trajectories and map from above (paper Fig. 11)",
            "Estimated (solid) and true (dashed) paths of every vehicle and the landmark map, "
            "coloured by the vehicle that observed each landmark.",
        )
    if tl_path.exists() and ev_path.exists():
        timeline = pd.read_csv(tl_path)
        events = pd.read_csv(ev_path)
        add(
            figs.landmark_uncertainty(timeline, events, t0),
            "landmark_uncertainty",
            "Landmark uncertainty over time (paper Fig. 12)",
            "RMS standard deviation of the landmarks updated in each frame; loop closures "
            "(lines) and re-observations of other vehicles' landmarks (type 2, shaded).",
        )
        add(
            figs.feature_counts(timeline, t0),
            "feature_counts",
            "Features per frame by type",
            "Type 1: re-observations of the vehicle's own landmarks; type 2: landmarks mapped "
            "by another vehicle; type 3: new landmarks.",
        )
    for v in vehicles:
        pairs = [
            ("fuse_single", "fuse", "single vs cooperative (paper Fig. 13/17)", "coop"),
            ("fuse_ekf", "fuse", "EKF vs NH-infinity", "filters"),
        ]
        for a, b, what, tag in pairs:
            ests = [by[(r, v)] for r in (a, b, "deadreckoning") if (r, v) in by]
            if (a, v) in by and (b, v) in by:
                add(
                    figs.error_over_time(
                        _truth_series(v, truth[v], t0),
                        [_series(e, t0) for e in ests],
                        f"{v}: {what}",
                    ),
                    f"error_{tag}_{v}",
                    f"{v}: position error, {what}",
                    "Position error against the ground truth over time; RMSE in the legend.",
                )
    main_nees = {v: nees_of[(main_run, v)] for v in vehicles if (main_run, v) in nees_of}
    nees_t = {v: (st - t0) * 1e-9 for v, (st, _) in main_nees.items()}
    nees = {v: n for v, (_, n) in main_nees.items()}
    if nees:
        add(
            figs.nees_over_time(
                nees_t,
                nees,
                _nees_band(cfg),
                3,
            ),
            "nees",
            "Position NEES over time",
            "Normalised estimation error squared of each vehicle's position "
            f"({RUN_LABELS[main_run]}) and the {100 * cfg.nees_band_probability:.0f} % "
            "chi-square band (3 dof): a consistent filter stays inside it.",
        )
    mosaic_dir = run_dir / MOSAIC_DIR
    if mosaic_dir.is_dir():
        images = {}
        for name in [*vehicles, "all"]:
            p = mosaic_dir / f"{name}.png"
            if p.exists():
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                scale = 1200.0 / max(img.shape[:2])
                if scale < 1:
                    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                images[name] = img
        if images:
            add(
                figs.mosaics(images),
                "mosaics",
                "Ground mosaics (paper Figs. 19-21)",
                "Each vehicle's mosaic from its fused poses and the merged one: the team covers "
                "more ground than any one vehicle (docs/mosaic.md).",
            )
    return entries


# --------------------------------------------------------------------------- stage


def run(
    cfg: Config,
    run_dir: Path,
    *,
    gt: Sequence[str] = (),
    log_paths: Sequence[Path] = (),
    force: bool = False,
) -> EvalSummary:
    t_start = time.perf_counter()
    rd = RunDir(run_dir)
    runs = _runs_present(run_dir)
    if not runs:
        raise CvslamError(
            f"{run_dir}: no fuse output (fuse*/<vehicle>.tum); run `cvslam fuse` first"
        )
    vehicles = _vehicles_of(run_dir / runs[0])
    truth, truth_files, truth_source = _ground_truth(cfg, run_dir, gt, vehicles, log_paths)
    est_files = sorted(
        p for r in runs for p in (run_dir / r).iterdir()
        if p.suffix in (".tum", ".csv", ".npz")
    )  # fmt: skip
    mosaic_files = (
        sorted((run_dir / MOSAIC_DIR).glob("*.png")) if (run_dir / MOSAIC_DIR).is_dir() else []
    )
    out_dir = run_dir / "eval"
    outputs = [out_dir / n for n in ("metrics.json", "metrics.csv", "headline.csv", "report.html")]
    plan = rd.plan(
        "eval", cfg, ("eval",), [*truth_files, *est_files, *mosaic_files], outputs, force
    )
    if plan.action == "skip":
        log.info("eval: %s is up to date (same config and inputs); --force to redo it", out_dir)
        old = pd.read_csv(out_dir / "headline.csv", index_col=0)
        return EvalSummary(run_dir, out_dir, True, old, pd.read_csv(out_dir / "metrics.csv"))
    estimates = [e for e in _estimates(run_dir, runs, vehicles) if e.vehicle in truth]
    rows = []
    nees_of = {}
    for e in estimates:
        try:
            row, nees_series = _metrics(e, truth[e.vehicle], cfg.eval)
        except ValueError as exc:  # no matching stamps, degenerate alignment
            raise CvslamError(
                f"{e.path}: cannot be compared with the ground truth of {e.vehicle} "
                f"({truth_source}): {exc}"
            ) from None
        rows.append(row)
        if nees_series is not None:
            nees_of[(e.run, e.vehicle)] = nees_series
    metrics = pd.DataFrame(rows)
    headline = _headline(metrics)

    tmp = out_dir.with_name("eval.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    entries = _figures(run_dir, tmp, estimates, truth, headline, nees_of, cfg.eval)
    metrics.to_csv(tmp / "metrics.csv", index=False)  # full precision (repr)
    headline.to_csv(tmp / "headline.csv")
    provenance = {
        "run directory": str(run_dir.resolve()),
        "ground truth": truth_source,
        "cvslam version": __version__,
        "evaluated": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "alignment": cfg.eval.align,
        **{f"input {r['path']}": f"sha256 {r['sha256'][:16]}..., {r['size']} bytes"
           for r in map(input_record, truth_files)},
    }  # fmt: skip
    stages = rd.load().get("stages", {})
    for name in (*runs, MOSAIC_DIR, "extract"):
        if name in stages:
            st = stages[name]
            provenance[f"stage {name}"] = (
                f"{st.get('finished', '?')}, config {st.get('config_digest', '?')}"
            )
    metrics_json = {
        "cvslam_version": __version__,
        "align": cfg.eval.align,
        "ground_truth": truth_source,
        "headline_ate_rmse_m": {
            v: {k: _num(x) for k, x in row.items()} for v, row in headline.iterrows()
        },
        "estimates": [{k: _num(x) for k, x in r.items()} for r in rows],
    }
    write_text_atomic(tmp / "metrics.json", json.dumps(metrics_json, indent=2) + "\n")
    report_metrics = metrics.set_index("vehicle")
    html = render_report(
        title=f"cvslam evaluation: {run_dir.name}",
        subtitle=f"{len(truth)} vehicle(s), estimates: "
        + ", ".join(dict.fromkeys(e.label for e in estimates)),
        headline=headline,
        headline_note="ATE RMSE in metres against the ground truth "
        f"({'no alignment' if cfg.eval.align == 'none' else cfg.eval.align + ' alignment'}).",
        figures=entries,
        metrics=report_metrics,
        config_yaml=dump_config(cfg),
        provenance=provenance,
    )
    write_text_atomic(tmp / "report.html", html)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    tmp.rename(out_dir)
    wall = time.perf_counter() - t_start
    rd.record(
        "eval",
        plan,
        outputs,
        {
            "headline_ate_rmse_m": {
                v: {k: None if x is None else round(x, 4) for k, x in row.items()}
                for v, row in metrics_json["headline_ate_rmse_m"].items()
            },
            "figures": len(entries),
        },
        wall,
    )
    return EvalSummary(run_dir, out_dir, False, headline, metrics, wall)


def _num(x: Any) -> Any:
    if isinstance(x, (float, np.floating)):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    return x


def headline_text(headline: pd.DataFrame) -> str:
    """The headline table as aligned text for the terminal."""
    return headline.to_string(float_format=lambda x: f"{x:.2f}", na_rep="-")
