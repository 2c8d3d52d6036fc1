"""`make bench`: cooperative vs single-vehicle fuse with 2 and 4 UAVs (issue 6).

Scenarios: `configs/scenarios/uav2_paper.yaml` (2 UAVs) and `uav4_team.yaml` (the same two
plus uav3 and uav4, which start at 16 s and 24 s, fly alone over new ground for ~25 s and
then over ground the others mapped), landmark mode (`cvslam simulate --set mode=landmarks`),
the full 60 s missions, the simulator's default IMU and landmarks. Every fuse setting is the
config's default (NH-infinity, gamma 10, bound on the vehicle states; at most
`fuse.map.max_landmarks` 150 landmarks in the state with one vehicle, plus
`landmarks_per_added_vehicle` 100 per other vehicle, up to `max_landmarks_total` 400: 150
alone, 250 for 2 UAVs, 400 for 4; `slam.landmark_bound`).

1. Monte Carlo: seeds 1 .. N_RUNS (seed 1 is the scenarios' own; the seed changes the
   terrain, the landmarks, the IMU and the observation noise, not the paths), each scenario
   simulated once per seed, and on the same data: cooperative (all vehicles in one filter,
   `Slam(inputs)`, as `cvslam fuse`), single (each vehicle in its own filter, as `cvslam fuse
   --single`) and dead reckoning (the same IMU input, no vision). Per vehicle and mode:
   position RMSE over the runs at each frame, over all frames and runs, at the final frame;
   position NEES e^T P^-1 e (3 dof; P the 3x3 position block of the pose covariance)
   averaged over the runs at each frame, its time average and the fraction of frames inside
   the 95 % band of the mean of N chi-square(3) variables (each vehicle's first frame left
   out); per-run RMSE ratio cooperative / single (geometric mean and 95 % interval); the
   type-1 observations per frame, the type-2 observations (landmarks mapped by another
   vehicle) and the landmarks created.
2. Speed (seed 1, each run alone in a fresh process, BLAS limited to one thread as the
   stage): real-time factor (flight seconds / wall seconds of `Slam.run`) of uav1 alone,
   the 2 UAVs and the 4 UAVs cooperative; time per frame (the timeline's `ms`) and the
   state size. Target from the issue: >= 5x real time for 2 UAVs
   (printed, not asserted: DESIGN.md convention 8).
3. The bound on the landmarks in the state with more vehicles: the cooperative filter
   again with at most L landmarks in the state whatever the number of vehicles
   (`fuse.map.max_landmarks` = `max_landmarks_total` = L, none per added vehicle), L in
   BOUNDS (default 150 and 600: 150 was the shared bound before it grew with the vehicles;
   600 = 150 per vehicle for 4 UAVs without the total), on the first N_BOUND_RUNS seeds
   (an L equal to the default's bound for that team is the default run): RMSE per
   vehicle, landmarks created, mean state size, type-1 observations per frame, type-2
   observations, divergences.

Per-frame curves go to `runs/benchmarks/fuse_coop.csv`, the summary to
`fuse_coop_summary.csv`, the speed runs' timelines to `fuse_coop_speed.csv` and the bound
runs to `fuse_coop_bound.csv` (gitignored).

A filter that raises is recorded with the run (its vehicles' errors NaN, left out of the
statistics) and the other runs go on.

Asserted, per team: at the default bound no run diverges or raises, every estimate is
finite, and vision keeps every vehicle's RMSE below half of dead reckoning's (cooperative
and single); with 2 UAVs the later-starting uav2's RMSE over all runs and frames is lower
cooperative than single. The same for the later-starting vehicles of the 4-UAV team is a
strict xfail: at commit a1b74c9 it does not hold for uav3 (3.83 m cooperative vs 3.53 m
alone over 6 seeds, worse in 5 of them; uav2 and uav4 gain; BENCHMARKS.md, "Fuse:
cooperative, 2 and 4 vehicles"). Nothing about NEES is asserted (reported: far above the
band, as in the one-vehicle Monte Carlo). Nothing about the other bounds is asserted.

Run time: ~10 min on the 2-core machine with the defaults (5 seeds, 2 of them with the
other bounds). Environment: CVSLAM_COOP_RUNS (default 5), CVSLAM_COOP_BOUND_RUNS (default
2), CVSLAM_COOP_BOUNDS (default "150,600"), CVSLAM_COOP_WORKERS (default min(2, CPUs)),
CVSLAM_COOP_SIM (a folder to keep the simulations in and reuse; default a temporary one).
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from numpy.typing import NDArray
from scipy.stats import chi2
from threadpoolctl import threadpool_limits

from cvslam_cli.config import Config, load_config
from cvslam_cli.estimation import stage
from cvslam_cli.estimation.settings import landmark_bound
from cvslam_cli.estimation.slam import Slam, SlamResult, dead_reckoning_track
from cvslam_cli.estimation.vehicle import VehicleInput
from cvslam_cli.geometry.rotations import interpolate_positions
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.parallel import STATE, ordered_map
from cvslam_cli.records.arrays import F64
from cvslam_cli.records.poses import PoseTable
from cvslam_cli.sim.scenario import SCENARIO_DIR, load_scenario
from cvslam_cli.sim.stage import SIM_EPOCH_NS
from cvslam_cli.sim.stage import run as simulate

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


ROOT = Path(__file__).resolve().parents[2]
OUT_DIR = ROOT / "runs" / "benchmarks"
N_RUNS = int(os.environ.get("CVSLAM_COOP_RUNS", "5"))
N_BOUND_RUNS = min(N_RUNS, int(os.environ.get("CVSLAM_COOP_BOUND_RUNS", "2")))
BOUNDS = tuple(int(b) for b in os.environ.get("CVSLAM_COOP_BOUNDS", "150,600").split(",") if b)
WORKERS = int(os.environ.get("CVSLAM_COOP_WORKERS", str(min(2, os.cpu_count() or 1))))
SEEDS = list(range(1, N_RUNS + 1))
SCENARIOS = {2: "uav2_paper", 4: "uav4_team"}  # vehicles -> scenario
SIM_SETS = ("mode=landmarks",)
# settings where the pixel noise does not enter (the filter's kind and bound, the map's
# bound): no frames are measured for it
NO_PIXELS = 0.5
MODES = ("coop", "single", "deadreckoning")
SPEED_TARGET_2 = 5.0  # x real time, 2 UAVs cooperative (issue 6)
TIME_MARKS_S = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0)


# ----------------------------------------------------------------------------- inputs


def _sim(name: str, seed: int, cache: Path, workers: int = 1) -> Path:
    """The scenario `name` simulated with `seed` in landmark mode, under `cache` (reused
    when already there: the simulator renames a complete output into place)."""
    out = cache / f"{name}_seed{seed}"
    if not (out / "features").is_dir():
        sc = load_scenario(SCENARIO_DIR / f"{name}.yaml", SIM_SETS, seed=seed)
        simulate(sc, out, force=True, workers=workers)
    return out


def _inputs(cfg: Config, sim: Path) -> tuple[list[VehicleInput], dict[str, PoseTable]]:
    files = sorted((sim / "features").glob("*.npz"))
    features = {fs.vehicle: fs for fs, _ in (load_features(p) for p in files)}
    logs = LogSet([McapLogSource(p) for p in sorted(sim.glob("*.mcap"))], cfg.logs)
    return stage.build_inputs(cfg, features, logs)


def _frames(vin: VehicleInput) -> NDArray[np.int64]:
    """The stamps of the frames the filter processes (from the vehicle's start)."""
    st = vin.features.frame_stamp_ns
    return st[st >= vin.start_ns]


def default_bound(cfg: Config, n_vehicles: int) -> int:
    """Landmarks in the state at most with the config's defaults (as `Slam`)."""
    return landmark_bound(stage.slam_settings(cfg.fuse, "hinf", NO_PIXELS), n_vehicles)


def shared_bound(total: int) -> Config:
    """The config with at most `total` landmarks in the state whatever the vehicles."""
    return load_config(
        (),
        [
            f"fuse.map.max_landmarks={total}",
            "fuse.map.landmarks_per_added_vehicle=0",
            f"fuse.map.max_landmarks_total={total}",
        ],
    )


# ----------------------------------------------------------------------------- one run


@dataclass(frozen=True, eq=False)
class Track:
    """One vehicle in one mode: e (F, 3) position error, P (F, 3, 3) position covariance
    (NaN after a divergence)."""

    e: F64
    P: F64


@dataclass(frozen=True, eq=False)
class FilterStats:
    """What one filter run (cooperative, or the single runs together) did."""

    failed: str  # "": ran to the end; else the divergences ("vehicle at t s: reason") and
    # the runs that raised
    landmarks: float  # landmarks created (NaN if the filter raised)
    type1: dict[str, float]  # type-1 observations per frame, per vehicle
    type2: dict[str, int]  # type-2 observations, per vehicle
    state_size: float  # mean over frames
    wall_s: float


@dataclass(frozen=True, eq=False)
class RunResult:
    scenario: str
    seed: int
    t_s: dict[str, F64]  # per vehicle (F,) frame times from the scenario's start
    tracks: dict[tuple[str, str], Track]  # (mode, vehicle); modes: MODES, f"shared{bound}"
    stats: dict[str, FilterStats]  # mode -> stats (not dead reckoning)


def _track(vin: VehicleInput, gt: F64, res_track: Any) -> Track:
    """The track's errors at the vehicle's frames (NaN where it has none; all NaN for None:
    the filter raised)."""
    st = _frames(vin)
    e = np.full((len(st), 3), np.nan)
    P = np.full((len(st), 3, 3), np.nan)
    if res_track is None:
        return Track(e, P)
    at = np.searchsorted(st, res_track.stamps_ns)
    e[at] = res_track.p_nav_m - gt[at]
    P[at] = res_track.pose_cov[:, :3, :3]
    return Track(e, P)


def _stats(results: list[SlamResult], crashed: list[str], wall_s: float, t0_ns: int) -> FilterStats:
    rows = [row for r in results for row in r.timeline]
    tl = pd.DataFrame(rows, columns=list(rows[0]) if rows else ["vehicle", "type1", "type2"])
    div = [r.divergence for r in results if r.divergence is not None]
    failed = [f"{d.vehicle} at {(d.stamp_ns - t0_ns) * 1e-9:.1f} s: {d.reason}" for d in div]
    by = tl.groupby("vehicle")
    return FilterStats(
        failed="; ".join(failed + crashed),
        landmarks=sum(len(r.landmarks) for r in results) if results else float("nan"),
        type1={str(k): float(v) for k, v in by["type1"].mean().items()},
        type2={str(k): int(v) for k, v in by["type2"].sum().items()},
        state_size=float(tl["state_size"].mean()) if rows else float("nan"),
        wall_s=wall_s,
    )


def _run_filter(
    inputs: list[VehicleInput], cfg: Config, single: bool
) -> tuple[list[SlamResult], list[str], float]:
    """(results, crashes, wall s): one filter over all `inputs`, or one per vehicle. A filter
    that raises is recorded (with its vehicles) and the other runs go on."""
    settings = stage.settings_for(cfg.fuse, "hinf", inputs)
    groups = [[v] for v in inputs] if single else [inputs]
    results, crashed = [], []
    t0 = time.perf_counter()
    for group in groups:
        try:
            results.append(Slam(group, settings).run())
        except Exception as exc:  # a bug in the filter: reported by the health test
            names = "+".join(v.name for v in group)
            crashed.append(f"{names} raised {type(exc).__name__}: {exc}")
    return results, crashed, time.perf_counter() - t0


def one_run(job: tuple[str, int]) -> RunResult:
    """Simulate one (scenario, seed) and run every mode on it (for `ordered_map`)."""
    name, seed = job
    cache = Path(STATE["sim_cache"])
    cfg = load_config((), [])
    with threadpool_limits(limits=1, user_api="blas"):
        inputs, truth = _inputs(cfg, _sim(name, seed, cache))
        t0_ns = SIM_EPOCH_NS
        gts = {
            v.name: interpolate_positions(
                truth[v.name].stamps_ns, truth[v.name].p_nav_m, _frames(v)
            )
            for v in inputs
        }
        t_s = {v.name: (_frames(v) - t0_ns) * 1e-9 for v in inputs}
        tracks: dict[tuple[str, str], Track] = {}
        stats: dict[str, FilterStats] = {}
        runs = [("coop", cfg, False), ("single", cfg, True)]
        if seed in SEEDS[:N_BOUND_RUNS]:
            for b in STATE["bounds"]:
                if b != default_bound(cfg, len(inputs)):  # else the same run as "coop"
                    runs.append((f"shared{b}", shared_bound(b), False))
        for mode, c, single in runs:
            results, crashed, wall = _run_filter(inputs, c, single)
            for v in inputs:
                tr = next((r.tracks[v.name] for r in results if v.name in r.tracks), None)
                tracks[mode, v.name] = _track(v, gts[v.name], tr)
            stats[mode] = _stats(results, crashed, wall, t0_ns)
        for v in inputs:
            tracks["deadreckoning", v.name] = _track(v, gts[v.name], dead_reckoning_track(v))
    if not STATE["keep"]:
        shutil.rmtree(cache / f"{name}_seed{seed}", ignore_errors=True)
    return RunResult(name, seed, t_s, tracks, stats)


# ----------------------------------------------------------------------------- statistics


def nees_band(n_runs: int, dof: int = 3) -> tuple[float, float]:
    """Two-sided 95 % band of the mean of n_runs chi-square(dof) NEES values."""
    lo, hi = chi2.ppf([0.025, 0.975], dof * n_runs) / n_runs
    return float(lo), float(hi)


@dataclass(frozen=True, eq=False)
class Summary:
    """One vehicle in one mode over N runs: per frame (F,) RMSE and mean NEES; scalars
    over frames 1 .. F-1 (RMSE over all runs and frames; final: over runs at the last frame)."""

    n_runs: int
    t_s: F64
    rmse_t: F64
    nees_t: F64
    band: tuple[float, float]
    rmse_m: float
    final_rmse_m: float
    nees_mean: float
    in_band: float
    run_rmse_m: F64  # (N,)
    finite: bool  # every frame of every run has a finite estimate and covariance


def summarize(t_s: F64, e: F64, P: F64) -> Summary:
    """e (N, F, 3) errors, P (N, F, 3, 3) covariances (NaN where a filter stopped)."""
    n = e.shape[0]
    ok = np.isfinite(e).all(axis=2) & np.isfinite(P).all(axis=(2, 3))
    sq = np.where(ok, np.sum(np.where(ok[..., None], e, 0.0) ** 2, axis=2), np.nan)
    Pf = np.where(ok[..., None, None], P, np.eye(3))
    ef = np.where(ok[..., None], e, 0.0)
    nees = np.einsum("nfi,nfi->nf", ef, np.linalg.solve(Pf, ef[..., None])[..., 0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames after a divergence
        rmse_t = np.sqrt(np.nanmean(sq, axis=0))
        nees_t = np.nanmean(np.where(ok, nees, np.nan), axis=0)
        run_rmse = np.sqrt(np.nanmean(sq[:, 1:], axis=1))
    band = nees_band(n)
    inside = (nees_t[1:] >= band[0]) & (nees_t[1:] <= band[1])
    return Summary(
        n,
        t_s,
        rmse_t,
        nees_t,
        band,
        float(np.sqrt(np.nanmean(sq[:, 1:]))),
        float(rmse_t[-1]),
        float(np.nanmean(nees_t[1:])),
        float(inside.mean()),
        run_rmse,
        bool(ok.all()),
    )


def _rms(e: F64) -> float:
    """RMS of the norms of the finite rows of e (..., 3); NaN if there are none."""
    sq = np.sum(e**2, axis=-1)
    ok = np.isfinite(sq)
    return float(np.sqrt(np.mean(sq[ok]))) if ok.any() else float("nan")


def ratio_ci(a: F64, b: F64) -> tuple[float, float, float, float, int]:
    """Over the runs where both are finite: geometric mean of the per-run ratios a/b, its
    95 % interval, the fraction of runs with a < b, and the number of runs."""
    ok = np.isfinite(a) & np.isfinite(b)
    lr = np.log(a[ok] / b[ok])
    n = len(lr)
    if n == 0:
        return float("nan"), float("nan"), float("nan"), float("nan"), 0
    m = float(lr.mean())
    half = 1.96 * lr.std(ddof=1) / np.sqrt(n) if n > 1 else np.inf
    win = float(np.mean(a[ok] < b[ok]))
    return float(np.exp(m)), float(np.exp(m - half)), float(np.exp(m + half)), win, n


@dataclass(frozen=True, eq=False)
class Team:
    """One scenario's Monte Carlo."""

    scenario: str
    vehicles: list[str]
    start_s: dict[str, float]
    runs: list[RunResult]
    summaries: dict[tuple[str, str], Summary] = field(default_factory=dict)  # (mode, vehicle)

    def mean_stat(self, mode: str, what: str, vehicle: str | None = None) -> float:
        vals = []
        for r in self.runs:
            if mode not in r.stats:
                continue
            v = getattr(r.stats[mode], what)
            vals.append(v.get(vehicle, np.nan) if vehicle is not None else v)
        return float(np.nanmean(vals)) if np.isfinite(vals).any() else float("nan")

    def failed(self, mode: str) -> list[str]:
        """Runs of `mode` that diverged or raised."""
        return [
            f"seed {r.seed}: {r.stats[mode].failed}"
            for r in self.runs
            if mode in r.stats and r.stats[mode].failed
        ]


def make_team(name: str, runs: list[RunResult]) -> Team:
    vehicles = sorted(runs[0].t_s)
    team = Team(name, vehicles, {v: float(runs[0].t_s[v][0]) for v in vehicles}, runs)
    for mode in (*MODES, *(f"shared{b}" for b in BOUNDS)):
        rs = [r for r in runs if (mode, vehicles[0]) in r.tracks]
        if not rs:
            continue
        for v in vehicles:
            for r in rs:
                if len(r.t_s[v]) != len(rs[0].t_s[v]):
                    raise AssertionError(f"{name} seed {r.seed}: {v} frames differ")
            e = np.stack([r.tracks[mode, v].e for r in rs])
            P = np.stack([r.tracks[mode, v].P for r in rs])
            team.summaries[mode, v] = summarize(rs[0].t_s[v], e, P)
    return team


# ----------------------------------------------------------------------------- report


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _table(title: str, head: list[str], rows: list[list[str]]) -> None:
    print(f"\n{title}")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")


def _print_team(team: Team) -> None:
    n = len(team.runs)
    band = team.summaries["coop", team.vehicles[0]].band
    rows = []
    for v in team.vehicles:
        single = team.summaries["single", v]
        for mode in MODES:
            s = team.summaries[mode, v]
            ratio = win = t1 = t2 = "-"
            if mode == "coop":
                r, lo, hi, w, k = ratio_ci(s.run_rmse_m, single.run_rmse_m)
                of = "" if k == n else f" of {k}"
                ratio = f"{r:.2f} ({lo:.2f} .. {hi:.2f})"
                win = f"{w:.0%}{of}"
            if mode != "deadreckoning":
                t1 = f"{team.mean_stat(mode, 'type1', v):.1f}"
                t2 = f"{team.mean_stat(mode, 'type2', v):.0f}"
            rows.append(
                [v, f"{team.start_s[v]:.0f}", mode, f"{s.rmse_m:.3f}", f"{s.final_rmse_m:.3f}",
                 f"{s.nees_mean:.1f}", f"{s.in_band:.0%}", ratio, win, t1, t2]
            )  # fmt: skip
    _table(
        f"{len(team.vehicles)} vehicles ({team.scenario}, landmarks), {n} runs x 60 s; "
        f"95% band of the mean NEES (3 dof, N = {n}): {band[0]:.2f} .. {band[1]:.2f}",
        ["vehicle", "start s", "mode", "RMSE m", "final m", "NEES mean", "in band",
         "coop/single RMSE (95% CI)", "coop lower in", "type1/frame", "type2"],
        rows,
    )  # fmt: skip
    for mode in ("coop", "single"):
        print(
            f"{mode}: landmarks created {team.mean_stat(mode, 'landmarks'):.0f}, mean state "
            f"size {team.mean_stat(mode, 'state_size'):.0f}, diverged or raised "
            f"{len(team.failed(mode))} / {n} {team.failed(mode) or ''}"
        )
    rows = []
    for v in team.vehicles:
        for mode in MODES:
            s = team.summaries[mode, v]
            at = np.searchsorted(s.t_s, TIME_MARKS_S).clip(max=len(s.t_s) - 1)
            marks = zip(s.rmse_t[at], TIME_MARKS_S, strict=True)
            vals = [f"{x:.2f}" if t >= s.t_s[0] else "-" for x, t in marks]
            rows.append([v, mode, *vals])
    _table(
        "position RMSE (m) over the runs at t (scenario time)",
        ["vehicle", "mode", *(f"{t:.0f} s" for t in TIME_MARKS_S)],
        rows,
    )


def _print_bounds(teams: dict[int, Team], cfg: Config) -> None:
    if not BOUNDS or not N_BOUND_RUNS:
        return
    rows = []
    m = cfg.fuse.map
    for nv, team in teams.items():
        default = default_bound(cfg, nv)
        seeds = SEEDS[:N_BOUND_RUNS]
        variants = sorted({default, *BOUNDS})
        for b in variants:
            mode = "coop" if b == default else f"shared{b}"
            runs = [r for r in team.runs if mode in r.stats and r.seed in seeds]
            if not runs:
                continue
            label = (
                f"{b} (default: {m.max_landmarks} + {m.landmarks_per_added_vehicle} per added "
                f"vehicle, <= {m.max_landmarks_total})"
                if b == default
                else str(b)
            )
            errs = []
            for v in team.vehicles:
                e = np.stack([r.tracks[mode, v].e for r in runs])
                errs.append(f"{_rms(e[:, 1:]):.2f}")
            st = [r.stats[mode] for r in runs]
            rows.append(
                [str(nv), label, str(len(runs)), " / ".join(errs),
                 f"{np.nanmean([s.landmarks for s in st]):.0f}",
                 f"{np.nanmean([s.state_size for s in st]):.0f}",
                 f"{np.nanmean([np.mean(list(s.type1.values())) for s in st if s.type1]):.1f}",
                 f"{np.mean([sum(s.type2.values()) for s in st]):.0f}",
                 f"{np.mean([s.wall_s for s in st]):.1f}",
                 f"{sum(bool(s.failed) for s in st)}"]
            )  # fmt: skip
    _table(
        "cooperative filter vs the bound on landmarks in the state, all vehicles together "
        "(same seeds; wall s measured with the Monte Carlo's 2 parallel workers)",
        ["vehicles", "state bound", "runs", "RMSE m per vehicle", "landmarks created",
         "mean state size", "type1/frame", "type2", "wall s", "diverged or raised"],
        rows,
    )  # fmt: skip
    for team in teams.values():
        for b in BOUNDS:
            for d in team.failed(f"shared{b}"):
                print(f"{team.scenario} bound {b} diverged or raised: {d}")


def _write_csv(teams: dict[int, Team]) -> None:
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    curves, summary, bound = [], [], []
    for nv, team in teams.items():
        for (mode, v), s in team.summaries.items():
            head = {"vehicles": nv, "scenario": team.scenario, "vehicle": v, "mode": mode}
            curves.append(
                pd.DataFrame(
                    {**head, "frame": np.arange(len(s.t_s)), "t_s": s.t_s, "rmse_m": s.rmse_t,
                     "nees_mean": s.nees_t, "band_lo": s.band[0], "band_hi": s.band[1]}
                )
            )  # fmt: skip
            summary.append(
                {**head, "runs": s.n_runs, "rmse_m": s.rmse_m, "final_rmse_m": s.final_rmse_m,
                 "nees_mean": s.nees_mean, "in_band": s.in_band, "band_lo": s.band[0],
                 "band_hi": s.band[1]}
            )  # fmt: skip
        for r in team.runs:
            for mode, st in r.stats.items():
                for v in team.vehicles:
                    e = r.tracks[mode, v].e
                    bound.append(
                        {"vehicles": nv, "scenario": team.scenario, "seed": r.seed,
                         "mode": mode, "vehicle": v,
                         "rmse_m": _rms(e[1:]),
                         "type1_per_frame": st.type1.get(v), "type2": st.type2.get(v),
                         "landmarks": st.landmarks, "state_size": st.state_size,
                         "wall_s": st.wall_s, "failed": st.failed}
                    )  # fmt: skip
    pd.concat(curves).to_csv(OUT_DIR / "fuse_coop.csv", index=False, float_format="%.6g")
    summary_csv = OUT_DIR / "fuse_coop_summary.csv"
    pd.DataFrame(summary).to_csv(summary_csv, index=False, float_format="%.6g")
    pd.DataFrame(bound).to_csv(OUT_DIR / "fuse_coop_bound.csv", index=False, float_format="%.6g")
    print(f"\nper-frame curves, summary, per-run rows: {OUT_DIR}/fuse_coop*.csv")


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def sim_cache() -> Iterator[tuple[Path, bool]]:
    """(folder, keep): where the simulations go; kept only under CVSLAM_COOP_SIM."""
    keep = os.environ.get("CVSLAM_COOP_SIM")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        yield Path(keep), True
        return
    tmp = Path(tempfile.mkdtemp(prefix="fuse_coop_"))
    try:
        yield tmp, False
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config((), [])


# ----------------------------------------------------------------------------- 2. speed


@dataclass(frozen=True)
class SpeedSpec:
    label: str
    sim: str
    vehicles: tuple[str, ...]  # run together in one filter


@dataclass(frozen=True, eq=False)
class SpeedRow:
    spec: SpeedSpec
    frames: int
    flight_s: float
    wall_s: float
    ms: F64  # (frames,)
    state_size: float
    landmarks: int
    rmse_m: dict[str, float]
    diverged: bool


def speed_run(spec: SpeedSpec) -> SpeedRow:
    """One filter run alone in this (fresh) process."""
    cfg = load_config((), [])
    with threadpool_limits(limits=1, user_api="blas"):
        inputs, truth = _inputs(cfg, Path(spec.sim))
        chosen = [v for v in inputs if v.name in spec.vehicles]
        settings = stage.settings_for(cfg.fuse, "hinf", chosen)
        t0 = time.perf_counter()
        res = Slam(chosen, settings).run()
        wall = time.perf_counter() - t0
    start = min(v.start_ns for v in chosen)
    flight = max(int(_frames(v)[-1]) - start for v in chosen) * 1e-9
    rmse = {}
    for v in chosen:
        tr = res.tracks[v.name]
        err = tr.p_nav_m - interpolate_positions(
            truth[v.name].stamps_ns, truth[v.name].p_nav_m, tr.stamps_ns
        )
        rmse[v.name] = float(np.sqrt(np.nanmean(np.sum(err**2, axis=1))))
    tl = pd.DataFrame(res.timeline)
    return SpeedRow(
        spec,
        len(tl),
        flight,
        wall,
        tl["ms"].to_numpy(float),
        float(tl["state_size"].mean()),
        len(res.landmarks),
        rmse,
        res.divergence is not None,
    )


def test_speed_vs_vehicles(sim_cache: tuple[Path, bool]) -> None:
    cache, _ = sim_cache
    load0 = _load()
    t0 = time.perf_counter()
    sims = {nv: str(_sim(name, SEEDS[0], cache, workers=2)) for nv, name in SCENARIOS.items()}
    sim_s = time.perf_counter() - t0
    specs = [
        SpeedSpec("1: uav1 alone", sims[2], ("uav1",)),
        SpeedSpec("2: uav2_paper cooperative", sims[2], ("uav1", "uav2")),
        SpeedSpec("4: uav4_team cooperative", sims[4], ("uav1", "uav2", "uav3", "uav4")),
    ]
    ctx = multiprocessing.get_context("spawn")
    # one process per run (maxtasksperchild=1), one at a time: nothing else of ours runs
    with ctx.Pool(1, maxtasksperchild=1) as pool:
        rows = pool.map(speed_run, specs, chunksize=1)
    print(
        f"\n[bench] speed: seed {SEEDS[0]}, simulated in {sim_s:.0f} s; load average "
        f"{load0} before, {_load()} after the runs"
    )
    _table(
        "whole run, NH-inf, default landmark bound (150, +100 per added vehicle, up to 400), "
        "one BLAS thread, each run in a fresh process",
        ["vehicles", "frames", "flight s", "wall s", "real time", "ms/frame mean",
         "median", "p95", "mean state size", "landmarks created", "RMSE m"],
        [
            [r.spec.label, str(r.frames), f"{r.flight_s:.1f}", f"{r.wall_s:.2f}",
             f"{r.flight_s / r.wall_s:.1f}x", f"{r.ms.mean():.2f}",
             f"{np.median(r.ms):.2f}", f"{np.percentile(r.ms, 95):.2f}",
             f"{r.state_size:.0f}", str(r.landmarks),
             " / ".join(f"{x:.2f}" for x in r.rmse_m.values())]
            for r in rows
        ],
    )  # fmt: skip
    two = rows[1]
    rt = two.flight_s / two.wall_s
    print(
        f"target >= {SPEED_TARGET_2:g}x real time for 2 UAVs cooperative: "
        f"{rt:.1f}x, {'met' if rt >= SPEED_TARGET_2 else 'NOT met'}"
    )
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    pd.concat(
        pd.DataFrame({"run": r.spec.label, "frame": np.arange(r.frames), "ms": r.ms}) for r in rows
    ).to_csv(OUT_DIR / "fuse_coop_speed.csv", index=False, float_format="%.4g")
    for r in rows:
        assert not r.diverged, r.spec
        assert np.isfinite(r.ms).all() and all(np.isfinite(list(r.rmse_m.values())))


# ----------------------------------------------------------------------------- 1. and 3.


@pytest.fixture(scope="module")
def teams(sim_cache: tuple[Path, bool], cfg: Config) -> dict[int, Team]:
    cache, keep = sim_cache
    load0 = _load()
    t0 = time.perf_counter()
    # the 4-UAV runs first: the longest jobs first keep both workers busy to the end
    jobs = [(SCENARIOS[nv], s) for nv in (4, 2) for s in SEEDS]
    state = {"sim_cache": str(cache), "keep": keep, "bounds": BOUNDS}
    results = list(ordered_map(one_run, jobs, workers=WORKERS, state=state))
    wall = time.perf_counter() - t0
    out = {
        nv: make_team(name, [r for r in results if r.scenario == name])
        for nv, name in SCENARIOS.items()
    }
    print(
        f"\n[bench] cooperative Monte Carlo: {N_RUNS} seeds x 2 scenarios, the default "
        f"bound and state bounds {BOUNDS} on {N_BOUND_RUNS} seeds, {WORKERS} workers, "
        f"{wall:.0f} s wall; load average {load0} before, {_load()} after"
    )
    for team in out.values():
        _print_team(team)
    _print_bounds(out, cfg)
    _write_csv(out)
    return out


@pytest.mark.parametrize("n_vehicles", sorted(SCENARIOS))
def test_healthy_and_beat_dead_reckoning(teams: dict[int, Team], n_vehicles: int) -> None:
    team = teams[n_vehicles]
    for mode in ("coop", "single"):
        assert not team.failed(mode), (team.scenario, mode, team.failed(mode))
    for v in team.vehicles:
        dr = team.summaries["deadreckoning", v]
        for mode in ("coop", "single"):
            s = team.summaries[mode, v]
            assert s.finite, (team.scenario, mode, v)
            assert s.rmse_m < 0.5 * dr.rmse_m, (team.scenario, mode, v, s.rmse_m, dr.rmse_m)


def _later(team: Team) -> list[str]:
    return [v for v in team.vehicles if team.start_s[v] > min(team.start_s.values())]


def _coop_vs_single(team: Team) -> list[str]:
    worse = []
    for v in _later(team):
        c, s = team.summaries["coop", v], team.summaries["single", v]
        if not c.rmse_m <= s.rmse_m:
            worse.append(f"{v}: cooperative RMSE {c.rmse_m:.3f} m > single {s.rmse_m:.3f} m")
    return worse


def test_cooperation_helps_the_later_uav_of_two(teams: dict[int, Team]) -> None:
    assert not _coop_vs_single(teams[2]), _coop_vs_single(teams[2])


@pytest.mark.xfail(
    strict=True,
    reason="4 UAVs at the default bound (400 in all): uav3 is worse "
    "cooperative than alone (3.83 vs 3.53 m over 6 seeds at a1b74c9; BENCHMARKS.md, 'Fuse: "
    "cooperative, 2 and 4 vehicles')",
)
def test_cooperation_helps_the_later_uavs_of_four(teams: dict[int, Team]) -> None:
    assert not _coop_vs_single(teams[4]), _coop_vs_single(teams[4])
