"""The figures of `cvslam eval`'s report, after Nemra & Aouf 2012 (Figs. 10-13, 17, 19-21).

Every builder takes arrays and DataFrames (no file reading here) and returns a
`matplotlib.figure.Figure` made with the object-oriented API on the Agg canvas: no pyplot,
no figure manager, no global state beyond the style applied while a figure is built and
rendered. Sizes are fixed (`DPI`, the `*_SIZE_IN` constants; `png_bytes` renders exactly
width x height x `DPI` pixels) and the output is deterministic.

The nav frame is NED (x north, y east, z down); figures show north, east and height (-z)
and say so in their labels. Times are seconds since the mission start.

Colours: one tab10 colour per vehicle (`vehicle_colours`), the same in every figure and in
`cvslam mosaic`'s overlays when the fleet is given in the same order; pass
`colours=vehicle_colours(fleet)` to every builder to keep them when figures show different
subsets of the fleet (by default, the vehicles a figure shows take tab10 in name order).
Figures comparing runs of one vehicle (errors, RMSE bars) colour by run label instead
(`run_colour`): ground truth black, dead reckoning grey.

- position_components (Fig. 10): north, east, height over time; truth, DR, estimate +-3 sigma
- top_view (Fig. 11): paths (east right, north up) and landmarks by observer
- landmark_uncertainty (Fig. 12): landmark sigma over time, loop closures, shared landmarks
- error_over_time (Figs. 13, 17): position error norm of several runs with their RMSE
- feature_counts (Fig. 3's feature types): type 1/2/3 features per frame per vehicle
- nees_over_time (consistency): NEES per vehicle with the chi-square band, from each
  vehicle's first informative value
- mosaics (Figs. 19-21): the per-vehicle mosaics and the merged one, with scale bars
- headline_bars (summary): position RMSE per vehicle and run
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import matplotlib
import matplotlib.style
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_hex
from matplotlib.figure import Figure
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from cvslam_cli.geometry.georef import scale_bar_m
from cvslam_cli.geometry.rotations import interpolate_positions
from cvslam_cli.records.arrays import F64, check_increasing

DPI = 120
COMPONENTS_SIZE_IN = (8.0, 7.5)
TOP_VIEW_SIZE_IN = (9.0, 7.0)
UNCERTAINTY_SIZE_IN = (9.0, 4.5)
ERROR_SIZE_IN = (9.0, 4.5)
FEATURES_WIDTH_IN = 9.0
FEATURES_ROW_IN = 2.5  # height per vehicle; plus FEATURES_EXTRA_IN for titles and labels
FEATURES_EXTRA_IN = 1.0
NEES_SIZE_IN = (9.0, 4.5)
MOSAIC_PANEL_IN = (4.5, 5.0)  # width, height of one mosaic panel
BARS_SIZE_IN = (8.0, 4.5)
LOG_ERROR_RATIO = 20.0  # error_over_time: log y axis when the RMSEs differ more than this

LOOP_CLOSURE = "loop_closure"
CROSS_VEHICLE = "cross_vehicle"

TRUTH_COLOUR = "#000000"
DEAD_RECKONING_COLOUR = "#7f7f7f"
SHARED_LANDMARK_COLOUR = "#505050"
DEAD_RECKONING_LABEL = "dead reckoning"
GROUND_TRUTH_LABEL = "ground truth"
# colours of the runs compared in `error_over_time` and `headline_bars` (ColorBrewer Dark2,
# unlike tab10's vehicle colours); other labels take _EXTRA_RUN_COLOURS in order
_RUN_COLOURS = {
    "cooperative NH-inf": "#1b9e77",
    "single NH-inf": "#d95f02",
    "cooperative EKF": "#7570b3",
    "single EKF": "#e7298a",
    DEAD_RECKONING_LABEL: DEAD_RECKONING_COLOUR,
    GROUND_TRUTH_LABEL: TRUTH_COLOUR,
}
_EXTRA_RUN_COLOURS = ("#66a61e", "#e6ab02", "#a6761d", "#1f78b4", "#b15928")
_FEATURE_TYPES = (
    ("type1", "type 1: re-observed, own landmark", "#1b9e77"),
    ("type2", "type 2: re-observed, another vehicle's", "#d95f02"),
    ("type3", "type 3: new, initialised", "#7570b3"),
)
_RC = {
    "font.size": 9.0,
    "axes.titlesize": 10.0,
    "axes.labelsize": 9.0,
    "legend.fontsize": 8.0,
    "xtick.labelsize": 8.0,
    "ytick.labelsize": 8.0,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "grid.linewidth": 0.6,
    "figure.facecolor": "white",
    "savefig.facecolor": "white",
    "image.interpolation": "antialiased",
}
_TIME_LABEL = "time since mission start [s]"
_COMPONENTS = (  # (index in p_m, sign, axis label)
    (0, 1.0, "north x [m]"),
    (1, 1.0, "east y [m]"),
    (2, -1.0, "height −z [m] (up)"),
)


@dataclass(frozen=True, eq=False)
class Series:
    """One trajectory of one vehicle. t_s (K,) seconds since the mission start, strictly
    increasing; p_m (K, 3) nav positions (NED: north, east, down); sigma_m (K, 3) 1-sigma per
    axis (NaN where unknown) or None. `label` names the run, e.g. "cooperative NH-inf",
    "single NH-inf", "cooperative EKF", "dead reckoning", "ground truth"."""

    vehicle: str
    label: str
    t_s: np.ndarray
    p_m: np.ndarray
    sigma_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=np.float64)
        p = np.asarray(self.p_m, dtype=np.float64)
        where = f"Series {self.vehicle} {self.label!r}"
        if t.ndim != 1 or len(t) == 0 or p.shape != (len(t), 3):
            raise ValueError(f"{where}: need t_s (K,) and p_m (K, 3), got {t.shape}, {p.shape}")
        if not np.all(np.isfinite(t)):
            raise ValueError(f"{where}: t_s must be finite")
        check_increasing(f"{where}: t_s", t)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "p_m", p)
        if self.sigma_m is not None:
            s = np.asarray(self.sigma_m, dtype=np.float64)
            if s.shape != p.shape:
                raise ValueError(f"{where}: sigma_m must be (K, 3), got {s.shape}")
            object.__setattr__(self, "sigma_m", s)


# --------------------------------------------------------------------------- helpers


def vehicle_colours(vehicles: Sequence[str]) -> dict[str, str]:
    """Vehicle name -> hex colour: tab10 in the given order (the fleet's order, as the
    mosaic overlays use), repeating after ten vehicles."""
    tab10 = matplotlib.colormaps["tab10"].colors
    return {v: to_hex(tab10[i % len(tab10)]) for i, v in enumerate(dict.fromkeys(vehicles))}


def run_colour(label: str, others: Sequence[str] = ()) -> str:
    """The colour of a run label: fixed for the known runs, else the next extra colour by the
    label's position among the unknown `others` (the figure's labels in drawing order)."""
    if label in _RUN_COLOURS:
        return _RUN_COLOURS[label]
    unknown = [o for o in dict.fromkeys(others) if o not in _RUN_COLOURS]
    i = unknown.index(label) if label in unknown else len(unknown)
    return _EXTRA_RUN_COLOURS[i % len(_EXTRA_RUN_COLOURS)]


@contextlib.contextmanager
def _style() -> Iterator[None]:
    """matplotlib's defaults plus the report's sizes, whatever the user's matplotlibrc says."""
    with matplotlib.style.context(["default", _RC]):
        yield


def _figure(size_in: tuple[float, float]) -> Figure:
    fig = Figure(figsize=size_in, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _colours_for(colours: Mapping[str, str] | None, names: Sequence[str]) -> dict[str, str]:
    if colours is None:
        return vehicle_colours(sorted(set(names)))
    missing = sorted(set(names) - set(colours))
    if missing:
        raise ValueError(f"no colour given for vehicle(s) {', '.join(missing)}")
    return dict(colours)


def _require(frame: pd.DataFrame, columns: Sequence[str], what: str) -> None:
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise ValueError(f"{what}: missing column(s) {', '.join(missing)}")


def _seconds(stamps_ns: pd.Series, t0_ns: int) -> F64:
    return (stamps_ns.to_numpy(dtype=np.int64) - np.int64(t0_ns)) / 1e9


def _vehicle_rows(frame: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """(vehicle, its rows in stamp order) in order of first appearance."""
    return [
        (str(v), frame[frame["vehicle"] == v].sort_values("stamp_ns", kind="stable"))
        for v in pd.unique(frame["vehicle"])
    ]


def position_error_m(truth: Series, estimate: Series) -> F64:
    """(K,) |p_estimate - p_truth| at the estimate's stamps, truth interpolated linearly;
    NaN where the truth does not cover the stamp."""
    return np.linalg.norm(
        estimate.p_m - interpolate_positions(truth.t_s, truth.p_m, estimate.t_s), axis=1
    )


def rmse_m(errors_m: np.ndarray) -> float:
    """Root mean square of the finite errors; NaN when there are none."""
    e = np.asarray(errors_m, dtype=np.float64)
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")


def _legend(ax: Axes, **kwargs: object) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**{"loc": "upper left", "framealpha": 0.85, **kwargs})


# --------------------------------------------------------------------------- figures


def position_components(
    truth: Series,
    estimate: Series,
    dead_reckoning: Series | None = None,
    *,
    colours: Mapping[str, str] | None = None,
) -> Figure:
    """Paper Fig. 10: north, east and height of one vehicle over time (three stacked axes).

    Each axis draws, in this order, `ax.lines`: the truth (black, dashed), the dead
    reckoning (grey, dotted; when given), the estimate (the vehicle's colour); and
    `ax.collections[0]`: the estimate +-3 sigma band where `estimate.sigma_m` is finite.
    Each series is drawn on its own stamps; the truth is interpolated at the estimate's
    stamps only for the axis' right title "truth inside ±3σ: P%" (share of the stamps with
    both a truth and a finite sigma).
    """
    series = [truth, estimate] + ([dead_reckoning] if dead_reckoning is not None else [])
    if len({s.vehicle for s in series}) != 1:
        raise ValueError(f"series of different vehicles: {sorted({s.vehicle for s in series})}")
    colour = _colours_for(colours, [estimate.vehicle])[estimate.vehicle]
    truth_at_est = interpolate_positions(truth.t_s, truth.p_m, estimate.t_s)
    with _style():
        fig = _figure(COMPONENTS_SIZE_IN)
        axes = fig.subplots(3, 1, sharex=True)
        for ax, (k, sign, ylabel) in zip(axes, _COMPONENTS, strict=True):
            ax.plot(
                truth.t_s,
                sign * truth.p_m[:, k],
                color=TRUTH_COLOUR,
                ls="--",
                lw=1.2,
                label=truth.label,
            )
            if dead_reckoning is not None:
                ax.plot(
                    dead_reckoning.t_s,
                    sign * dead_reckoning.p_m[:, k],
                    color=DEAD_RECKONING_COLOUR,
                    ls=":",
                    lw=1.4,
                    label=dead_reckoning.label,
                )
            est = sign * estimate.p_m[:, k]
            ax.plot(estimate.t_s, est, color=colour, lw=1.2, label=estimate.label)
            if estimate.sigma_m is not None:
                three = 3.0 * estimate.sigma_m[:, k]
                ax.fill_between(
                    estimate.t_s,
                    est - three,
                    est + three,
                    color=colour,
                    alpha=0.22,
                    lw=0,
                    label=f"{estimate.label} ±3σ",
                )
                ref = sign * truth_at_est[:, k]
                ok = np.isfinite(ref) & np.isfinite(three)
                if ok.any():
                    inside = np.abs(ref[ok] - est[ok]) <= three[ok]
                    ax.set_title(f"truth inside ±3σ: {inside.mean():.0%}", loc="right", fontsize=8)
            ax.set_ylabel(ylabel)
        axes[-1].set_xlabel(_TIME_LABEL)
        handles, labels = axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=len(labels))
        fig.suptitle(
            f"{estimate.vehicle}: position in the nav frame (NED: x north, y east, z down)"
        )
    return fig


def top_view(
    tracks: Sequence[Series],
    truths: Sequence[Series],
    landmarks_ne: np.ndarray,
    landmark_vehicles: Sequence[str],
    *,
    colours: Mapping[str, str] | None = None,
) -> Figure:
    """Paper Fig. 11: the paths seen from above, east to the right and north up, equal
    aspect. landmarks_ne (N, 2) landmark north, east [m]; landmark_vehicles (N,) their
    observers joined by ';' (e.g. "uav1;uav2").

    Drawn in this order: `ax.collections`: one scatter of small dots per landmark group
    (seen by one vehicle only: its colour; by several: grey), then the start markers (one
    scatter, white circles edged in the vehicle's colour); `ax.lines`: each truth (dashed)
    then each track (solid; dotted for a "dead reckoning" track), all in the vehicle's
    colour, x = east, y = north."""
    lm = np.asarray(landmarks_ne, dtype=np.float64).reshape(-1, 2)
    observers = [tuple(sorted(set(str(o).split(";")) - {""})) for o in landmark_vehicles]
    if len(observers) != len(lm):
        raise ValueError(f"{len(lm)} landmarks but {len(observers)} observer entries")
    singles = sorted({o[0] for o in observers if len(o) == 1})
    names = [s.vehicle for s in (*truths, *tracks)] + singles
    col = _colours_for(colours, names)
    with _style():
        fig = _figure(TOP_VIEW_SIZE_IN)
        ax = fig.add_subplot()
        # (observer or "" for several, label, colour, marker area [pt^2]): the shared
        # landmarks (the paper's cooperatively initialised ones) larger, on top
        groups = [(v, f"landmarks seen by {v} only", col[v], 4.0) for v in singles]
        groups.append(("", "landmarks seen by several vehicles", SHARED_LANDMARK_COLOUR, 9.0))
        for v, label, c, area in groups:
            sel = np.array([(o == (v,)) if v else len(o) > 1 for o in observers], dtype=bool)
            if sel.any():
                ax.scatter(
                    lm[sel, 1], lm[sel, 0], s=area, color=c, alpha=0.7, lw=0, label=label, zorder=1
                )
        for s in truths:
            ax.plot(
                s.p_m[:, 1],
                s.p_m[:, 0],
                color=col[s.vehicle],
                ls="--",
                lw=1.1,
                label=f"{s.vehicle} {s.label}",
                zorder=2,
            )
        for s in tracks:
            ls = ":" if s.label == DEAD_RECKONING_LABEL else "-"
            ax.plot(
                s.p_m[:, 1],
                s.p_m[:, 0],
                color=col[s.vehicle],
                ls=ls,
                lw=1.6,
                label=f"{s.vehicle} {s.label}",
                zorder=3,
            )
        if tracks:
            starts = np.array([s.p_m[0, :2] for s in tracks])
            ax.scatter(
                starts[:, 1],
                starts[:, 0],
                s=45,
                facecolor="white",
                lw=1.8,
                edgecolor=[col[s.vehicle] for s in tracks],
                label="start",
                zorder=4,
            )
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("east y [m]")
        ax.set_ylabel("north x [m]")
        ax.set_title("Top view (nav frame NED seen from above): estimated and true paths")
        _legend(ax, loc="upper left", bbox_to_anchor=(1.01, 1.0), markerscale=2.0)
    return fig


def landmark_uncertainty(
    timeline: pd.DataFrame,
    events: pd.DataFrame,
    t0_ns: int,
    *,
    colours: Mapping[str, str] | None = None,
) -> Figure:
    """Paper Fig. 12: each vehicle's `sigma_landmark_m` (RMS standard deviation of the
    landmarks updated in the frame; NaN, a gap, where none was) over time,
    t = (stamp_ns - t0_ns) / 1e9 s.

    `ax.lines`: one line per vehicle (order of first appearance in `timeline`), then one
    dashed vertical line in the vehicle's colour at the start of each "loop_closure"
    event; `ax.patches`: one shaded span [stamp_ns, end_stamp_ns] in the vehicle's colour
    per "cross_vehicle" event (the vehicle re-observing another vehicle's landmarks).
    Other events are not drawn. `events` needs stamp_ns, end_stamp_ns, event, vehicle."""
    _require(timeline, ("stamp_ns", "vehicle", "sigma_landmark_m"), "timeline")
    _require(events, ("stamp_ns", "end_stamp_ns", "event", "vehicle"), "events")
    shown = events[events["event"].isin((LOOP_CLOSURE, CROSS_VEHICLE))]
    rows = _vehicle_rows(timeline)
    col = _colours_for(colours, [v for v, _ in rows] + [str(v) for v in shown["vehicle"]])
    with _style():
        fig = _figure(UNCERTAINTY_SIZE_IN)
        ax = fig.add_subplot()
        for v, r in rows:
            ax.plot(
                _seconds(r["stamp_ns"], t0_ns),
                r["sigma_landmark_m"].to_numpy(float),
                color=col[v],
                lw=1.2,
                label=v,
            )
        labelled: set[tuple[str, str]] = set()
        for ev in shown.sort_values("stamp_ns", kind="stable").itertuples(index=False):
            v, kind = str(ev.vehicle), str(ev.event)
            t_start = (int(ev.stamp_ns) - t0_ns) / 1e9
            if kind == LOOP_CLOSURE:
                label = f"loop closure ({v})"
            else:
                label = f"{v} re-observes another vehicle's landmarks"
            label = label if (kind, v) not in labelled else "_nolegend_"
            labelled.add((kind, v))
            if kind == LOOP_CLOSURE:
                ax.axvline(t_start, color=col[v], ls="--", lw=1.3, label=label)
            else:
                t_end = max((int(ev.end_stamp_ns) - t0_ns) / 1e9, t_start)
                ax.axvspan(t_start, t_end, color=col[v], alpha=0.12, lw=0.8, label=label)
        ax.set_ylim(bottom=0.0)
        ax.set_xlabel(_TIME_LABEL)
        ax.set_ylabel("landmark σ, RMS over updated landmarks [m]")
        ax.set_title("Landmark uncertainty, loop closures and shared landmarks")
        _legend(ax, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


def error_over_time(
    truth: Series,
    estimates: Sequence[Series],
    title: str,
) -> Figure:
    """Paper Figs. 13 and 17: the position error norm |p_estimate - p_truth| of several
    estimates of one vehicle over time, the truth interpolated linearly at each estimate's
    stamps (NaN, a gap, outside the truth's span). `ax.lines[i]` is `estimates[i]`, in its
    run colour, labelled "<label>: RMSE <r> m" over its finite errors. The y axis is
    logarithmic when the largest RMSE is over `LOG_ERROR_RATIO` times the smallest (dead
    reckoning next to SLAM; from 1/100 of the smallest RMSE up), linear from 0 otherwise."""
    if any(e.vehicle != truth.vehicle for e in estimates):
        raise ValueError(f"estimates of other vehicles than {truth.vehicle}")
    labels = [e.label for e in estimates]
    with _style():
        fig = _figure(ERROR_SIZE_IN)
        ax = fig.add_subplot()
        rmses = []
        for e in estimates:
            err = position_error_m(truth, e)
            rmses.append(rmse_m(err))
            ax.plot(
                e.t_s,
                err,
                color=run_colour(e.label, labels),
                lw=1.2,
                label=f"{e.label}: RMSE {rmses[-1]:.3f} m",
            )
        finite = [r for r in rmses if np.isfinite(r) and r > 0.0]
        if finite and max(finite) > LOG_ERROR_RATIO * min(finite):
            ax.set_yscale("log")
            ax.set_ylim(bottom=min(finite) / 100.0)  # hide the approach to 0 at the start
            ax.set_ylabel("position error |p̂ − p| [m] (log scale)")
        else:
            ax.set_ylim(bottom=0.0)
            ax.set_ylabel("position error |p̂ − p| [m]")
        ax.set_xlabel(_TIME_LABEL)
        ax.set_title(title)
        _legend(ax)
    return fig


def feature_counts(
    timeline: pd.DataFrame,
    t0_ns: int,
    *,
    colours: Mapping[str, str] | None = None,
    types: Sequence[str] = ("type1", "type2", "type3"),
) -> Figure:
    """The paper's feature types per frame (Fig. 3), one axis per vehicle (order of first
    appearance, titled in the vehicle's colour): `ax.lines` = the `types` drawn, of type 1
    (re-observed, own landmark), type 2 (re-observed, another vehicle's), type 3 (new),
    over time (a lone vehicle has no type 2: leave it out)."""
    unknown = sorted(set(types) - {c for c, _, _ in _FEATURE_TYPES})
    if unknown or not types:
        raise ValueError(f"feature types must be some of type1, type2, type3, got {types}")
    _require(timeline, ("stamp_ns", "vehicle", *types), "timeline")
    rows = _vehicle_rows(timeline)
    col = _colours_for(colours, [v for v, _ in rows])
    height = FEATURES_EXTRA_IN + FEATURES_ROW_IN * max(len(rows), 1)
    with _style():
        fig = _figure((FEATURES_WIDTH_IN, height))
        axes = fig.subplots(max(len(rows), 1), 1, sharex=True, squeeze=False)[:, 0]
        for ax, (v, r) in zip(axes, rows, strict=False):
            t = _seconds(r["stamp_ns"], t0_ns)
            for column, label, c in _FEATURE_TYPES:
                if column in types:
                    ax.plot(t, r[column].to_numpy(float), color=c, lw=1.0, label=label)
            ax.set_title(v, color=col[v], fontweight="bold")
            ax.set_ylabel("features per frame")
            ax.set_ylim(bottom=0.0)
        axes[-1].set_xlabel(_TIME_LABEL)
        handles, labels = axes[0].get_legend_handles_labels()
        if handles:
            fig.legend(handles, labels, loc="outside upper center", ncols=len(labels))
    return fig


def first_informative(values: np.ndarray, informative_from: float | None) -> int:
    """Index of the first finite value >= `informative_from` (0 when None or when no value
    reaches it: then everything is shown)."""
    if informative_from is None:
        return 0
    y = np.asarray(values, dtype=np.float64)
    reached = np.flatnonzero(np.isfinite(y) & (y >= informative_from))
    return int(reached[0]) if reached.size else 0


def nees_over_time(
    t_s: np.ndarray | Mapping[str, np.ndarray],
    nees: Mapping[str, np.ndarray],
    band: tuple[float, float],
    dof: int,
    *,
    colours: Mapping[str, str] | None = None,
    informative_from: float | None = None,
) -> Figure:
    """The normalised estimation error squared per vehicle over time, log y axis: t_s (T,)
    seconds shared by all vehicles, or vehicle -> its own (T_v,) seconds; nees vehicle ->
    (T,) or (T_v,) (NaN where unknown); band (lower, upper) of the chi-square acceptance
    region for `dof` degrees of freedom, shaded (`ax.patches[0]`).
    `ax.lines`: one line per vehicle in `nees`' order, labelled with its share of finite
    values inside the band (over all of them), then a dotted line at the expected value
    `dof`. With `informative_from`, each vehicle's line starts at its first value at least
    that large (`first_informative`; the label says how many were left out): a filter that
    starts at the true pose with a small covariance has a NEES near 0 at first (1e-27 and
    the like), which says nothing about its consistency and would stretch the log axis
    over twenty decades."""
    lo, hi = float(band[0]), float(band[1])
    if not 0.0 < lo < hi:
        raise ValueError(f"band must be 0 < lower < upper, got {band}")
    col = _colours_for(colours, list(nees))
    with _style():
        fig = _figure(NEES_SIZE_IN)
        ax = fig.add_subplot()
        ax.axhspan(
            lo,
            hi,
            color="#bbbbbb",
            alpha=0.35,
            lw=0,
            label=f"χ² band [{lo:.3g}, {hi:.3g}], dof {dof}",
        )
        for v, values in nees.items():
            t = np.asarray(t_s[v] if isinstance(t_s, Mapping) else t_s, dtype=np.float64)
            y = np.asarray(values, dtype=np.float64)
            if t.ndim != 1 or y.shape != t.shape:
                raise ValueError(f"nees[{v!r}]: shape {y.shape}, t_s has {t.shape}")
            ok = np.isfinite(y)
            share = f"{np.mean((y[ok] >= lo) & (y[ok] <= hi)):.0%} in band" if ok.any() else "none"
            k = first_informative(y, informative_from)
            skipped = (
                f"; {k} first pose{'s' * (k > 1)} < {informative_from:.2g} not drawn" if k else ""
            )
            ax.plot(t[k:], y[k:], color=col[v], lw=1.0, label=f"{v} ({share}{skipped})")
        ax.axhline(dof, color="#444444", ls=":", lw=1.0, label=f"expected value {dof}")
        ax.set_yscale("log")
        ax.set_xlabel(_TIME_LABEL)
        ax.set_ylabel("NEES (log scale)")
        ax.set_title("Filter consistency: normalised estimation error squared")
        _legend(ax, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return fig


def _rgb_image(name: str, image: np.ndarray) -> np.ndarray:
    """uint8 grey (H, W) as is; BGR (H, W, 3) -> RGB; BGRA (H, W, 4) -> RGBA."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4))):
        raise ValueError(
            f"mosaic {name!r}: need uint8 (H, W), (H, W, 3) or (H, W, 4) image, "
            f"got {img.dtype} {img.shape}"
        )
    if img.ndim == 2:
        return img
    return img[..., [2, 1, 0, 3]] if img.shape[2] == 4 else img[..., ::-1]


def mosaics(
    images: dict[str, np.ndarray], *, merged: str, gsd_m: Mapping[str, float] | None = None
) -> Figure:
    """Paper Figs. 19-21: the mosaics side by side in `images`' order (north up), one axis
    each titled with its name (`merged` names the merged mosaic). Images are uint8 grey,
    BGR, or BGRA whose alpha marks no-data (shown transparent, on the white figure).
    `gsd_m`: metres per pixel of the images given (after any resizing); each of those gets
    a scale bar (`ax.artists[0]`, an `AnchoredSizeBar` of a round length, about a quarter
    of its width, in the lower left corner)."""
    n = max(len(images), 1)
    gsd_m = gsd_m or {}
    with _style():
        fig = _figure((MOSAIC_PANEL_IN[0] * n, MOSAIC_PANEL_IN[1]))
        axes = fig.subplots(1, n, squeeze=False)[0]
        for ax, (name, image) in zip(axes, images.items(), strict=False):
            img = _rgb_image(name, image)
            if img.ndim == 2:
                ax.imshow(img, cmap="gray", vmin=0, vmax=255)
            else:
                ax.imshow(img)
            title = "all vehicles (merged)" if name == merged else name
            ax.set_title(f"{title}  ({img.shape[1]} x {img.shape[0]} px, north up)")
            ax.set_axis_off()
            if name in gsd_m:
                _scale_bar(ax, img.shape[1], float(gsd_m[name]))
    return fig


def _scale_bar(ax: Axes, width_px: int, gsd_m: float) -> None:
    """A scale bar on an image axis (data units = pixels) of `gsd_m` metres per pixel."""
    if not (np.isfinite(gsd_m) and gsd_m > 0):
        raise ValueError(f"mosaic scale: need metres per pixel > 0, got {gsd_m}")
    length_m = scale_bar_m(width_px * gsd_m)
    bar = AnchoredSizeBar(
        ax.transData,
        length_m / gsd_m,
        f"{length_m:g} m",
        "lower left",
        pad=0.4,
        borderpad=0.6,
        sep=3,
        color="black",
        frameon=True,
        size_vertical=max(1.0, width_px / 150.0),
    )
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)


def headline_bars(table: pd.DataFrame) -> Figure:
    """Position RMSE [m] as grouped bars: one group per vehicle (the table's rows, index =
    vehicle names), one bar per run (its columns, e.g. "cooperative NH-inf", "single
    NH-inf", "cooperative EKF", "dead reckoning") in the run's colour, the value written
    above it. `ax.containers[j]` holds column j's bars; NaN (run absent) draws no bar."""
    vehicles = [str(v) for v in table.index]
    runs = [str(c) for c in table.columns]
    x = np.arange(len(vehicles), dtype=np.float64)
    width = 0.8 / max(len(runs), 1)
    with _style():
        fig = _figure(BARS_SIZE_IN)
        ax = fig.add_subplot()
        for j, run in enumerate(runs):
            values = table.iloc[:, j].to_numpy(dtype=np.float64)
            bars = ax.bar(
                x + (j - (len(runs) - 1) / 2) * width,
                np.nan_to_num(values, nan=0.0),
                width,
                color=run_colour(run, runs),
                label=run,
            )
            ax.bar_label(
                bars,
                labels=["" if np.isnan(r) else f"{r:.2f}" for r in values],
                fontsize=7,
                padding=1,
            )
        ax.set_xticks(x, vehicles)
        ax.set_ylabel("position RMSE [m]")
        ax.set_xlabel("vehicle")
        ax.set_title("Position RMSE per vehicle and run")
        ax.grid(axis="x", visible=False)
        ax.margins(y=0.12)
        _legend(ax)
    return fig


def png_bytes(fig: Figure) -> bytes:
    """`fig` rendered as a PNG of exactly its size x `DPI` pixels (no software stamp, so the
    same figure gives the same bytes), then closed (cleared; it must not be used afterwards).
    Rendering stays in memory: writing the bytes to a file is the stage's (`io/atomic.py`)."""
    buf = io.BytesIO()
    try:
        with _style():
            fig.savefig(buf, format="png", dpi=fig.dpi, metadata={"Software": None})
    finally:
        fig.clear()
    return buf.getvalue()
