"""`cvslam summary RUN_DIR...`: one table across runs, and a page comparing them.

One row per run x vehicle x estimate: the rows of each run's `eval/metrics.csv` as they are
(the numbers are that file's, to the last digit), behind the columns that say which row it
is (`run_dir`, `dataset`, `vehicle`, `estimate`), followed by the fuse run's wall time and
real-time factor (from `run.yaml`; empty for dead reckoning, which has no fuse run of its
own). Written as `<out>.csv` and `<out>.html` (a table, ATE RMSE per dataset and vehicle for
each estimate as bars, a link to each run's report).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from cvslam_cli.errors import CvslamError
from cvslam_cli.evaluation import figures as figs
from cvslam_cli.evaluation.report import render_summary
from cvslam_cli.io.atomic import write_text_atomic
from cvslam_cli.io.run_layout import RunLayout
from cvslam_cli.io.textfiles import read_yaml_mapping

KEY_COLUMNS = ("run_dir", "dataset", "vehicle", "estimate")
TIME_COLUMNS = ("fuse_wall_s", "realtime_factor")
# the columns of the page's table (the CSV has every metric)
PAGE_COLUMNS = (
    "ate_rmse_m",
    "ate_max_m",
    "rpe_frame_rmse_m",
    "rpe_drift_pct",
    "final_drift_pct",
    "nees_mean",
    "distance_m",
    *TIME_COLUMNS,
)


@dataclass(frozen=True)
class SummaryFiles:
    csv: Path
    html: Path
    rows: int


def _run_rows(run_dir: Path) -> pd.DataFrame:
    """The metrics rows of one run with the key and time columns."""
    layout = RunLayout(run_dir)
    path = layout.eval.metrics_csv
    if not path.is_file():
        raise CvslamError(f"{path}: not found; run `cvslam eval {run_dir}` (or `cvslam run`) first")
    try:
        rows = pd.read_csv(path)
    except (ValueError, pd.errors.ParserError) as exc:
        raise CvslamError(f"{path}: not a metrics table ({exc})") from None
    missing = {"run", "vehicle", "estimate"} - set(rows.columns)
    if missing:
        raise CvslamError(f"{path}: not a metrics table (no column {sorted(missing)[0]})")
    name = run_dir.resolve().name
    rows["run_dir"] = rows.get("run_dir", name)
    rows["dataset"] = rows.get("dataset", name)
    stages: dict[str, Any] = {}
    if layout.run_file.is_file():
        stages = read_yaml_mapping(layout.run_file, "a cvslam run record").get("stages", {})
    rows["fuse_wall_s"] = [stages.get(r, {}).get("wall_s", float("nan")) for r in rows["run"]]
    rows["realtime_factor"] = [
        stages.get(r, {}).get("summary", {}).get("realtime_factor", float("nan"))
        for r in rows["run"]
    ]
    return rows


def summary_table(run_dirs: Sequence[Path]) -> pd.DataFrame:
    """Every run's metrics rows, key columns first (module docstring)."""
    if not run_dirs:
        raise CvslamError("cvslam summary: no run directories given")
    table = pd.concat([_run_rows(r) for r in run_dirs], ignore_index=True)
    rest = [c for c in table.columns if c not in (*KEY_COLUMNS, *TIME_COLUMNS)]
    return table[[*KEY_COLUMNS, *rest, *TIME_COLUMNS]]


def _figure_png(table: pd.DataFrame) -> bytes:
    """ATE RMSE as grouped bars: one group per dataset / vehicle, one bar per estimate (in
    the report's order), on a log scale: dead reckoning is often 100x the filters' error."""
    from cvslam_cli.evaluation.stage import DR_LABEL, RUN_LABELS

    groups = table.assign(group=table["dataset"] + " / " + table["vehicle"].astype(str))
    wide = groups.pivot_table(index="group", columns="estimate", values="ate_rmse_m", sort=False)
    known = [*RUN_LABELS.values(), DR_LABEL]
    order = [c for c in known if c in wide.columns]
    wide = wide[order + [c for c in wide.columns if c not in order]]
    fig = figs.headline_bars(wide)
    ax = fig.axes[0]
    ax.set_yscale("log")
    ax.set_xlabel("dataset / vehicle")
    ax.set_title("ATE RMSE per dataset and vehicle, by estimate (log scale)")
    ax.tick_params(axis="x", labelrotation=20)
    fig.set_size_inches(max(8.0, 1.2 * len(wide)), 4.5)
    return figs.png_bytes(fig)


def write_summary(run_dirs: Sequence[Path], out: Path) -> SummaryFiles:
    """Write `<out>.csv` and `<out>.html` (`out` without a suffix; `.csv` is dropped)."""
    table = summary_table(run_dirs)
    stem = out.with_suffix("") if out.suffix in (".csv", ".html") else out
    csv_path, html_path = stem.with_name(stem.name + ".csv"), stem.with_name(stem.name + ".html")
    write_text_atomic(csv_path, table.to_csv(index=False))  # full precision, as metrics.csv
    page = table.set_index("run_dir")[
        ["dataset", "vehicle", "estimate", *[c for c in PAGE_COLUMNS if c in table]]
    ]
    reports = {}
    for run_dir in run_dirs:
        report = RunLayout(run_dir).eval.report_html
        url = os.path.relpath(report.resolve(), html_path.parent.resolve())
        reports[run_dir.resolve().name] = Path(url).as_posix()
    html = render_summary(
        title="cvslam summary",
        subtitle=f"{len(run_dirs)} run(s), {table['dataset'].nunique()} dataset(s), "
        f"{len(table)} rows (run x vehicle x estimate)",
        table=page,
        figure_png=_figure_png(table),
        figure_caption="ATE RMSE [m] of each estimate, per dataset and vehicle (each run's "
        "own alignment, eval.align). All metrics in " + csv_path.name + ".",
        reports=reports,
    )
    write_text_atomic(html_path, html)
    return SummaryFiles(csv_path, html_path, len(table))
