"""`make bench`: landmark-mode Monte Carlo of the fuse filters, EKF vs NH-infinity (issue 5).

Scenario: one UAV flying at 10 m/s over textured terrain with 20 m of relief, 100 m above
the nav origin, a downward stereo camera like `uav2_paper`'s (752x480, fx 450, baseline
1.5 m, 10 Hz), landmark mode (`cvslam simulate --set mode=landmarks`) with the simulator's
default landmark density, pixel noise and misses. The IMU is a consumer-grade one (10x the
simulator's default white noise, as in tests/estimation/test_stage.py) so dead reckoning
drifts by metres in the run, and the filter is told the same noise densities; every other
fuse setting (NH-infinity gamma, c_w, c_v, bound, margin; association; map) is the
config's default.

`N_RUNS` seeds (FIRST_SEED .. FIRST_SEED + N_RUNS - 1; the seed changes the terrain, the
landmarks, the IMU noise and the observation noise, nothing else) are simulated twice: with
`LEVELS` "default" (3 %) and "high" (20 %) of each frame's matches look-alike wrong matches
(`landmarks.lookalike_fraction`: a landmark in view imitated, its descriptor and disparity,
within `lookalike_offset_px` (5) of its own pixel: inside its innovation window as often as
not), beside the simulator's default 3 % of random ones (which the association never takes:
none in 87 000 observations, BENCHMARKS.md "Fuse: consistency (issue 15)"). The EKF and the
NH-infinity filter run on each simulated run (paired: the same data for both). The wrong
matches draw from the simulator's random stream, so the two levels of one seed are two
different realizations of the noise, not the same run with more wrong matches.

Per filter and level of look-alikes:
- position NEES e^T P^-1 e (e: 3-D position error against the ground truth, P: the 3x3
  position block of the pose covariance) averaged over the runs at each frame, its time
  average, and the fraction of frames inside the two-sided 95 % band of the mean of N
  chi-square(3) variables, chi2.ppf([0.025, 0.975], 3N) / N (frame 0 left out), and the
  time average's standard error over the runs (from each run's own time average: the frames
  of one run are strongly correlated, so a set of 50 runs is a small sample, and disjoint
  sets of 50 differ by several tenths; BENCHMARKS.md, "Fuse: consistency (issue 15)"). Each run
  starts from a draw of its prior around the true initial state (`tests.scenarios.from_prior`:
  the NEES is chi-square only then; CVSLAM_MC_START=truth starts at the truth itself, as this
  benchmark did before 2026-12-05, which reads below the band while the prior is forgotten);
- position RMSE over the runs at each frame, over all frames, and at the final frame;
  dead reckoning's (the same IMU input, no vision; NEES from the motion model's own
  covariance) for scale.
The per-frame curves go to `runs/benchmarks/fuse_consistency.csv` (gitignored), the
summary to `runs/benchmarks/fuse_consistency_summary.csv`.

Asserted: no run diverges or gives a non-finite state, and vision keeps the error far below
dead reckoning's. The issue's claim (with wrong matches injected, NH-infinity's position error is
lower than the EKF's) is printed with its ratio (and a paired 95 % interval of the per-run
ratio) and tested on its own at the default NH-infinity settings (gamma 30, c_w = c_v = 1):
it held by 0.2 % with the biased map of before issue 15 and no longer does (a strict xfail
carrying the figures: NH-infinity 1 % below the EKF would be a gain worth the name).
NEES is reported, not asserted here (`make test` has its own Monte Carlo NEES test,
tests/estimation/test_consistency.py; see BENCHMARKS.md, "Fuse: consistency (issue 15)").

Environment: CVSLAM_MC_SCENARIO (mc, the default: the scenario above, 15 s; loop: the same UAV
on a 60 m diamond 60 m up at 20 m/s, 30 s, `tests.scenarios.loop_uav_scenario`: landmarks in
view for ~3 s instead of ~10, a lap and a half), CVSLAM_MC_RUNS (default 50),
CVSLAM_MC_FIRST_SEED (default 0),
CVSLAM_MC_WORKERS (default min(2, CPUs)), CVSLAM_MC_START (prior, the default, or truth),
CVSLAM_MC_SET (config overrides for every filter, ";"-separated, e.g. "fuse.hinf.gamma=5").
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.stats import chi2
from threadpoolctl import threadpool_limits

from cvslam_cli.config import load_config
from cvslam_cli.estimation import stage
from cvslam_cli.estimation.slam import Slam, dead_reckoning_track
from cvslam_cli.geometry.rotations import (
    interpolate_poses,
    matrix_to_euler_zyx,
)
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.parallel import STATE, ordered_map
from cvslam_cli.records.arrays import F64
from cvslam_cli.sim.scenario import LandmarkMode, load_scenario
from cvslam_cli.sim.stage import run as simulate
from tests.scenarios import (
    MC_FILTER_OVERRIDES,
    VEHICLE,
    from_prior,
    loop_uav_scenario,
    monte_carlo_uav_scenario,
)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


ROOT = Path(__file__).resolve().parents[2]
OUT_DIR = ROOT / "runs" / "benchmarks"
N_RUNS = int(os.environ.get("CVSLAM_MC_RUNS", "50"))
FIRST_SEED = int(os.environ.get("CVSLAM_MC_FIRST_SEED", "0"))
WORKERS = int(os.environ.get("CVSLAM_MC_WORKERS", str(min(2, os.cpu_count() or 1))))
START = os.environ.get("CVSLAM_MC_START", "prior")
SCENARIOS = {  # name: (scenario builder, mission length s)
    "mc": (monte_carlo_uav_scenario, 15.0),
    "loop": (loop_uav_scenario, 30.0),
}
SCENARIO = os.environ.get("CVSLAM_MC_SCENARIO", "mc")
if SCENARIO not in SCENARIOS:
    raise ValueError(f"CVSLAM_MC_SCENARIO: {SCENARIO!r} is none of {', '.join(SCENARIOS)}")
DURATION_S = SCENARIOS[SCENARIO][1]
EXTRA_SETS = tuple(x for x in os.environ.get("CVSLAM_MC_SET", "").split(";") if x)
RANDOM_OUTLIERS = LandmarkMode().outlier_fraction
FILTERS = ("ekf", "hinf")
FUSE_NOISE = MC_FILTER_OVERRIDES


def scenario(lookalike_fraction: float, duration_s: float = DURATION_S) -> dict[str, Any]:
    """The Monte Carlo scenario (`SCENARIO`; seed set per run) with `lookalike_fraction`
    look-alike wrong matches beside the default random ones."""
    return SCENARIOS[SCENARIO][0](RANDOM_OUTLIERS, duration_s, lookalike_fraction)


# ----------------------------------------------------------------------------- one run


@dataclass(frozen=True, eq=False)
class FilterRun:
    """One filter on one simulated run: e (F, 3) position error, P (F, 3, 3) position
    covariance (NaN after a divergence), the same for the attitude (Euler angles, rad:
    e_att, P_att), and whether it diverged."""

    e: F64
    P: F64
    e_att: F64
    P_att: F64
    diverged: bool
    gamma_raised: int


@dataclass(frozen=True, eq=False)
class RunResult:
    seed: int
    t_s: F64  # (F,) frame times from the first frame
    filters: dict[str, FilterRun]
    e_dr: F64  # (F, 3) dead reckoning's position error
    P_dr: F64  # (F, 3, 3) and covariance (the motion model's alone)


def one_run(seed: int) -> RunResult:
    """Simulate `seed` with STATE's scenario file and run the filters with STATE's config
    overrides (for `ordered_map`)."""
    sc = load_scenario(Path(STATE["scenario"]), seed=seed)
    cfg = load_config((), [*FUSE_NOISE, *STATE["overrides"]])
    filters: dict[str, FilterRun] = {}
    with (
        threadpool_limits(limits=1, user_api="blas"),
        tempfile.TemporaryDirectory(prefix="fuse_mc_") as tmp,
    ):
        out = Path(tmp) / "sim"
        simulate(sc, out)
        features = {VEHICLE: load_features(out / "features" / f"{VEHICLE}.npz")[0]}
        logs = LogSet([McapLogSource(out / f"{VEHICLE}.mcap")], cfg.logs)
        inputs, truth = stage.build_inputs(cfg, features, logs)
        if STATE["from_prior"]:  # started from a draw of the prior (tests/scenarios.py)
            inputs = from_prior(inputs, seed)
        stamps = inputs[0].features.frame_stamp_ns
        g = truth[VEHICLE]
        gt, R_gt, _ = interpolate_poses(g.stamps_ns, g.p_nav_m, g.q_nav_body_xyzw, stamps)
        euler_gt = np.array([matrix_to_euler_zyx(R) for R in R_gt])
        for kind in STATE["filters"]:
            res = Slam(inputs, stage.settings_for(cfg.fuse, kind, inputs)).run()
            tr = res.tracks[VEHICLE]
            e = np.full((len(stamps), 3), np.nan)
            P = np.full((len(stamps), 3, 3), np.nan)
            at = np.searchsorted(stamps, tr.stamps_ns)
            e[at] = tr.p_nav_m - gt[at]
            P[at] = tr.pose_cov[:, :3, :3]
            e_att, P_att = np.full_like(e, np.nan), np.full_like(P, np.nan)
            e_att[at] = (tr.euler_rad - euler_gt[at] + np.pi) % (2 * np.pi) - np.pi
            P_att[at] = tr.pose_cov[:, 3:, 3:]
            bad = res.divergence is not None or not np.isfinite(e).all()
            filters[kind] = FilterRun(e, P, e_att, P_att, bad, res.gamma_raised)
        dr = dead_reckoning_track(inputs[0])
        at = np.searchsorted(dr.stamps_ns, stamps)
        e_dr = dr.p_nav_m[at] - gt
        P_dr = dr.pose_cov[at, :3, :3]
    t_s = (stamps - stamps[0]) * 1e-9
    return RunResult(seed, t_s, filters, e_dr, P_dr)


def monte_carlo(
    seeds: range | list[int],
    lookalike_fraction: float,
    overrides: tuple[str, ...] = (),
    filters: tuple[str, ...] = FILTERS,
    workers: int = WORKERS,
) -> list[RunResult]:
    """Every seed simulated with `lookalike_fraction` look-alike wrong matches and filtered
    by each of `filters` with the config's defaults plus `overrides` (`fuse.hinf.gamma=2`,
    ...)."""
    with tempfile.TemporaryDirectory(prefix="fuse_mc_sc_") as tmp:
        path = Path(tmp) / "scenario.yaml"
        path.write_text(yaml.safe_dump(scenario(lookalike_fraction)))
        state = {
            "scenario": str(path),
            "overrides": tuple(overrides),
            "filters": filters,
            "from_prior": START == "prior",
        }
        return list(ordered_map(one_run, list(seeds), workers=workers, state=state))


# ----------------------------------------------------------------------------- statistics


@dataclass(frozen=True, eq=False)
class Summary:
    """Over N runs, per frame (F,): mean NEES, RMSE; scalars over frames 1..F-1
    (`nees_mean_se`: the standard error of `nees_mean` from the runs' own time averages)."""

    n_runs: int
    t_s: F64
    nees_t: F64
    rmse_t: F64
    band: tuple[float, float]
    nees_mean: float
    nees_mean_se: float
    in_band: float
    rmse_m: float
    final_rmse_m: float
    run_rmse_m: F64  # (N,) each run's RMSE over frames
    diverged: int
    gamma_raised: int


def nees_band(n_runs: int, dof: int = 3) -> tuple[float, float]:
    """Two-sided 95 % band of the mean of n_runs chi-square(dof) NEES values."""
    lo, hi = chi2.ppf([0.025, 0.975], dof * n_runs) / n_runs
    return float(lo), float(hi)


def summarize_errors(t_s: F64, e: F64, P: F64) -> Summary:
    """e (N, F, 3) errors, P (N, F, 3, 3) covariances (NaN where a filter stopped)."""
    n = e.shape[0]
    sq = np.sum(e**2, axis=2)  # (N, F)
    rmse_t = np.sqrt(np.nanmean(sq, axis=0))
    run_rmse = np.sqrt(np.nanmean(sq[:, 1:], axis=1))
    band = nees_band(n)
    ok = np.isfinite(e).all(axis=2) & np.isfinite(P).all(axis=(2, 3))
    Pf = np.where(ok[..., None, None], P, np.eye(3))
    ef = np.where(ok[..., None], e, 0.0)
    nees = np.einsum("nfi,nfi->nf", ef, np.linalg.solve(Pf, ef[..., None])[..., 0])
    nees_run = np.where(ok, nees, np.nan)
    nees_t = np.nanmean(nees_run, axis=0)
    inside = (nees_t[1:] >= band[0]) & (nees_t[1:] <= band[1])
    nees_mean, in_band = float(np.nanmean(nees_t[1:])), float(inside.mean())
    per_run = np.nanmean(nees_run[:, 1:], axis=1)
    se = float(np.nanstd(per_run, ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    return Summary(
        n,
        t_s,
        nees_t,
        rmse_t,
        band,
        nees_mean,
        se,
        in_band,
        float(np.sqrt(np.nanmean(sq[:, 1:]))),
        float(rmse_t[-1]),
        run_rmse,
        0,
        0,
    )


def summarize(runs: list[RunResult], kind: str, attitude: bool = False) -> Summary:
    """Position (or, `attitude`, Euler angle) NEES and RMSE of filter `kind` over the runs."""
    t_s = runs[0].t_s
    for r in runs:
        if len(r.t_s) != len(t_s):
            raise AssertionError(f"seed {r.seed}: {len(r.t_s)} frames, seed 0 {len(t_s)}")
    if kind == "deadreckoning":
        return summarize_errors(
            t_s, np.stack([r.e_dr for r in runs]), np.stack([r.P_dr for r in runs])
        )
    e = np.stack([r.filters[kind].e_att if attitude else r.filters[kind].e for r in runs])
    P = np.stack([r.filters[kind].P_att if attitude else r.filters[kind].P for r in runs])
    s = summarize_errors(t_s, e, P)
    return replace(
        s,
        diverged=sum(r.filters[kind].diverged for r in runs),
        gamma_raised=sum(r.filters[kind].gamma_raised for r in runs),
    )


def paired_ratio(a: Summary, b: Summary) -> tuple[float, float, float]:
    """(RMSE ratio a/b over all runs and frames, mean per-run log-ratio's 95 % interval
    as ratios lo..hi)."""
    lr = np.log(a.run_rmse_m / b.run_rmse_m)
    half = 1.96 * lr.std(ddof=1) / np.sqrt(len(lr)) if len(lr) > 1 else np.inf
    m = lr.mean()
    return a.rmse_m / b.rmse_m, float(np.exp(m - half)), float(np.exp(m + half))


# ----------------------------------------------------------------------------- report


LEVELS = {"default": 0.03, "high": 0.20}  # look-alike wrong matches per frame's matches


@dataclass(frozen=True, eq=False)
class MonteCarlo:
    summaries: dict[tuple[str, str], Summary]  # (level, filter or "deadreckoning")
    wall_s: float


def _write_csv(mc: MonteCarlo) -> tuple[Path, Path]:
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    curves, table = OUT_DIR / "fuse_consistency.csv", OUT_DIR / "fuse_consistency_summary.csv"
    per_frame: list[pd.DataFrame] = []
    summary: list[dict[str, Any]] = []
    for (level, kind), s in mc.summaries.items():
        head = {"lookalikes": LEVELS[level], "filter": kind}
        band = {"band_lo": s.band[0], "band_hi": s.band[1]}
        per_frame.append(
            pd.DataFrame(
                {**head, "frame": np.arange(len(s.t_s)), "t_s": s.t_s, "nees_mean": s.nees_t,
                 **band, "rmse_m": s.rmse_t}
            )
        )  # fmt: skip
        summary.append(
            {**head, "runs": s.n_runs, "nees_mean": s.nees_mean, "nees_mean_se": s.nees_mean_se,
             **band, "in_band": s.in_band,
             "rmse_m": s.rmse_m, "final_rmse_m": s.final_rmse_m, "diverged": s.diverged,
             "gamma_raised": s.gamma_raised}
        )  # fmt: skip
    pd.concat(per_frame).to_csv(curves, index=False, float_format="%.6g")
    pd.DataFrame(summary).to_csv(table, index=False, float_format="%.6g")
    return curves, table


def _print_table(mc: MonteCarlo) -> None:
    print(
        f"\nfuse Monte Carlo ({SCENARIO}): {N_RUNS} runs "
        f"(seeds {FIRST_SEED}..{FIRST_SEED + N_RUNS - 1}) x "
        f"{DURATION_S:.0f} s per level of look-alike wrong matches, "
        f"{WORKERS} workers, {mc.wall_s:.0f} s wall"
    )
    band = next(iter(mc.summaries.values())).band
    print(f"95% band of the mean NEES (3 dof, N = {N_RUNS}): {band[0]:.2f} .. {band[1]:.2f}")
    print(
        f"{'lookalik':>8} {'filter':>15} {'NEES mean':>9} {'+-se':>5} {'in band':>7} {'RMSE m':>7} "
        f"{'final m':>7} {'diverged':>8} {'gamma up':>8}"
    )
    for (level, kind), s in mc.summaries.items():
        print(
            f"{LEVELS[level]:8.0%} {kind:>15} {s.nees_mean:9.2f} {s.nees_mean_se:5.2f} "
            f"{s.in_band:7.0%} {s.rmse_m:7.3f} "
            f"{s.final_rmse_m:7.3f} {s.diverged:8d} {s.gamma_raised:8d}"
        )
    marks = [t for t in (1.0, 3.0, 6.0, 9.0, 15.0, 20.0, 25.0) if t < DURATION_S] + [DURATION_S]
    print("mean NEES over time, t = " + ", ".join(f"{t:g}" for t in marks) + " s:")
    for (level, kind), s in mc.summaries.items():
        at = np.searchsorted(s.t_s, marks).clip(max=len(s.t_s) - 1)
        print(f"{LEVELS[level]:8.0%} {kind:>15} " + " ".join(f"{v:6.2f}" for v in s.nees_t[at]))
    for level in LEVELS:
        h, k = mc.summaries[level, "hinf"], mc.summaries[level, "ekf"]
        r, lo, hi = paired_ratio(h, k)
        wins = float(np.mean(h.run_rmse_m < k.run_rmse_m))
        print(
            f"{LEVELS[level]:.0%} look-alikes: NH-inf / EKF RMSE {h.rmse_m:.3f} / {k.rmse_m:.3f}"
            f" = {r:.3f} (per-run ratio 95% CI {lo:.3f} .. {hi:.3f}; NH-inf lower in "
            f"{wins:.0%} of runs); final {h.final_rmse_m:.3f} / {k.final_rmse_m:.3f} = "
            f"{h.final_rmse_m / k.final_rmse_m:.3f}"
        )


@pytest.fixture(scope="module")
def mc() -> MonteCarlo:
    t0 = time.perf_counter()
    summaries: dict[tuple[str, str], Summary] = {}
    for level, fraction in LEVELS.items():
        runs = monte_carlo(range(FIRST_SEED, FIRST_SEED + N_RUNS), fraction, EXTRA_SETS)
        for kind in (*FILTERS, "deadreckoning"):
            summaries[level, kind] = summarize(runs, kind)
        for kind in FILTERS:  # the attitude's NEES (its "RMSE m" column in radians)
            summaries[level, f"{kind} attitude"] = summarize(runs, kind, attitude=True)
    result = MonteCarlo(summaries, time.perf_counter() - t0)
    _print_table(result)
    curves, table = _write_csv(result)
    print(f"per-frame curves: {curves}\nsummary: {table}")
    return result


def test_filters_stay_healthy_and_beat_dead_reckoning(mc: MonteCarlo) -> None:
    for level in LEVELS:
        dr = mc.summaries[level, "deadreckoning"]
        for kind in FILTERS:
            s = mc.summaries[level, kind]
            assert s.diverged == 0, (level, kind, s.diverged)
            assert np.isfinite(s.nees_t[1:]).all() and np.isfinite(s.rmse_t).all()
            # vision keeps the position error a small fraction of dead reckoning's
            assert s.final_rmse_m < 0.25 * dr.final_rmse_m, (level, kind, s, dr)
            assert s.rmse_m < 0.5 * dr.rmse_m, (level, kind, s, dr)


@pytest.mark.xfail(
    strict=True,
    reason="issue 15: with a consistent filter NH-infinity at the default gamma 30, c_w = c_v = 1 "
    "equals the EKF (20 % look-alike wrong matches, 50 runs: RMSE 0.273 m both; gamma 5 0.999x, "
    "gamma 2 1.045x: its bound inflates the covariance, it does not reject wrong residuals); "
    'its earlier 0.2 % gain went with the overconfident map (BENCHMARKS.md, "Fuse: '
    'consistency (issue 15)", thirteenth step)',
)
def test_nh_infinity_position_error_below_ekf_with_outliers(mc: MonteCarlo) -> None:
    if SCENARIO != "mc":
        pytest.xfail(f"measured on the Monte Carlo scenario only, not {SCENARIO!r}")
    h, k = mc.summaries["high", "hinf"], mc.summaries["high", "ekf"]
    assert h.rmse_m < 0.99 * k.rmse_m, (
        f"{LEVELS['high']:.0%} look-alikes: NH-inf RMSE {h.rmse_m:.3f} m not 1 % below the EKF's "
        f"{k.rmse_m:.3f} m"
    )
