"""`make bench`: the cooperative filter on simulated images over several seeds (issues 15, 20).

The images runs move between seeds by more than most changes of the filter move them
(BENCHMARKS.md, "Fuse: eviction that keeps the landmarks in view": one eviction changes
everything after it), so a change is judged on several seeds, the way issue 15's goal 2 and
issue 20's checks read them. Settings chosen on seeds 1-5 held less well on seeds 6-10
(0.325 m against 0.252 before the bearing noise by octave, 0.248 against 0.199 with it:
BENCHMARKS.md, "Fuse: joint compatibility, and what a team's eviction spares", "Fuse: the
bearing noise by octave"): judge a change on seeds 1-10 (`CVSLAM_IMAGES_SEEDS=1,2,3,4,5,6,7,
8,9,10`). For each seed of CVSLAM_IMAGES_SEEDS (default "1,2,3,4,5") of
the scenario CVSLAM_IMAGES_SCENARIO (default `uav2_paper`): `cvslam simulate SCENARIO --seed N`
(rendered images), `cvslam extract`, `cvslam fuse` (cooperative NH-infinity, with the
overrides CVSLAM_IMAGES_SET, ";"-separated, e.g. "fuse.map.reactivation_inflation=64"),
`cvslam fuse --single` (the same overrides) and `cvslam eval`, each in a fresh process.

Printed per seed and vehicle: position RMSE (m, unaligned, against the simulator's truth),
mean position NEES (3 expected) and the share of poses in its 95 % band, cooperative and
single; then over all vehicle-seeds the mean cooperative RMSE, how many have a NEES <= 6
(issue 15's goal 2: twice the expected 3) and how many are below their single error
(issue 20's check). The table goes to `runs/benchmarks/fuse_images_seeds.csv` (gitignored).

A change is judged against a baseline in the same run: with CVSLAM_IMAGES_BASE_SET set
(";"-separated overrides; empty: the defaults) each seed's cooperative filter also runs at
those settings, on the same features (`run_baseline` beside `run`), and the print adds the
paired ratio of the two errors over the vehicle-seeds: its geometric mean, a 95 % interval
(the per-pair log ratios' mean +- 1.96 standard errors) and on how many the change is lower.
On these runs one association changes the evictions and everything after, moving single
vehicle-seeds by 30-80 % either way (BENCHMARKS.md, "Fuse: another vehicle's landmark, once
settled"): an interval that holds 1 is said to mean that the seeds do not tell the two apart.

Asserted: every command succeeds (no divergence) and every error is finite; nothing about
accuracy (DESIGN.md convention 8: figures are printed, the issue notes judge them).

Run time: ~2.5 min per seed on one core, most of it rendering and extraction; seeds run
CVSLAM_IMAGES_WORKERS (default 2) at a time, each command a process with one BLAS thread.
CVSLAM_IMAGES_SIM names a folder that keeps the simulations and feature files between runs
(the filters are always run again), so that comparing settings costs only the fuses.
CVSLAM_IMAGES_SIMULATE_SET (";"-separated) overrides the simulation itself, e.g.
"duration_s=30" for the 30 s `mixed_yard` missions of BENCHMARKS.md.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from tests.benchmarks.test_fuse_coop import ratio_ci

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "runs" / "benchmarks"


def _cvslam(*args: object) -> None:
    """`cvslam ARGS` in a fresh process; its stderr's end on failure."""
    r = subprocess.run(
        [sys.executable, "-m", "cvslam_cli", "-q", *map(str, args)], capture_output=True, text=True
    )
    assert r.returncode == 0, f"cvslam {' '.join(map(str, args))}: {r.stderr[-2000:]}"


def simulate_sets() -> list[str]:
    """`--set` arguments of CVSLAM_IMAGES_SIMULATE_SET, the simulation's own overrides."""
    return _set_args(_overrides("CVSLAM_IMAGES_SIMULATE_SET") or [])


def prepared(base: Path, scenario: str, seed: int) -> tuple[Path, Path]:
    """(sim, run) of one seed under `base`: simulated with images (and
    CVSLAM_IMAGES_SIMULATE_SET) and extracted unless kept there already."""
    sim, run = base / f"{scenario}_{seed}" / "sim", base / f"{scenario}_{seed}" / "run"
    if not (sim / "scenario.yaml").is_file():
        _cvslam("simulate", scenario, "-o", sim, "--seed", seed, "--force", *simulate_sets())
    if not (run / "features").is_dir():
        _cvslam("extract", *sorted(sim.glob("*.mcap")), "-o", run)
    return sim, run


def _evaluated(run: Path, seed: int, modes: dict[str, str]) -> list[dict[str, object]]:
    """`cvslam eval RUN`: the rows of the estimates whose first word is in `modes` (renamed
    as it says)."""
    _cvslam("eval", run, "--force")
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    rows = []
    for e in metrics["estimates"]:
        mode = e["estimate"].split()[0]  # "cooperative" / "single" / "dead"
        if mode in modes:
            rows.append(
                {"seed": seed, "vehicle": e["vehicle"], "mode": modes[mode],
                 "rmse_m": e["ate_rmse_m"], "nees": e["nees_mean"], "in_band": e["nees_in_band"]}
            )  # fmt: skip
    return rows


def _baseline_run(run: Path, name: str = "run_baseline") -> Path:
    """A run folder `name` beside `run` reading the same features (linked, else copied),
    for the baseline's cooperative filter."""
    other = run.parent / name
    other.mkdir(exist_ok=True)
    shutil.copy2(run / "run.yaml", other / "run.yaml")
    features = other / "features"
    if not features.exists():
        try:
            features.symlink_to((run / "features").resolve(), target_is_directory=True)
        except OSError:
            shutil.copytree(run / "features", features)
    return other


def _seed_run(
    base: Path, scenario: str, seed: int, sets: list[str], baseline: list[str] | None
) -> pd.DataFrame:
    """One seed: simulate and extract (unless kept), both fuses, eval; with `baseline`
    overrides also the cooperative filter at those (mode "baseline"); its rows."""
    _, run = prepared(base, scenario, seed)
    _cvslam("fuse", run, "--force", *_set_args(sets))
    _cvslam("fuse", run, "--single", "--force", *_set_args(sets))
    rows = _evaluated(run, seed, {"cooperative": "cooperative", "single": "single"})
    if baseline is not None:
        other = _baseline_run(run)
        _cvslam("fuse", other, "--force", *_set_args(baseline))
        rows += _evaluated(other, seed, {"cooperative": "baseline"})
    return pd.DataFrame(rows)


def _set_args(sets: list[str]) -> list[str]:
    """`--set K=V` for each override."""
    return [a for s in sets for a in ("--set", s)]


def _overrides(name: str) -> list[str] | None:
    """The ";"-separated overrides in environment variable `name` (None when it is unset)."""
    value = os.environ.get(name)
    return None if value is None else [s for s in value.split(";") if s.strip()]


def test_images_runs_over_seeds() -> None:
    scenario = os.environ.get("CVSLAM_IMAGES_SCENARIO", "uav2_paper")
    seeds = [int(s) for s in os.environ.get("CVSLAM_IMAGES_SEEDS", "1,2,3,4,5").split(",")]
    sets = _overrides("CVSLAM_IMAGES_SET") or []
    baseline = _overrides("CVSLAM_IMAGES_BASE_SET")
    workers = int(os.environ.get("CVSLAM_IMAGES_WORKERS", "2"))
    kept = os.environ.get("CVSLAM_IMAGES_SIM")
    with tempfile.TemporaryDirectory(prefix="cvslam_images_seeds_") as tmp:
        base = Path(kept) if kept else Path(tmp)
        # each seed's commands are processes of their own: threads only wait for them
        with ThreadPoolExecutor(max_workers=workers) as pool:
            parts = pool.map(lambda s: _seed_run(base, scenario, s, sets, baseline), seeds)
            table = pd.concat(list(parts))
    wide = table.pivot_table(index=["seed", "vehicle"], columns="mode",
                             values=["rmse_m", "nees", "in_band"])  # fmt: skip
    coop, single = wide[("rmse_m", "cooperative")], wide[("rmse_m", "single")]
    nees = wide[("nees", "cooperative")]
    OUT.mkdir(parents=True, exist_ok=True)
    table.to_csv(OUT / "fuse_images_seeds.csv", index=False)
    print(f"\n{scenario} with images, seeds {seeds}, overrides {sets or 'none'}")
    print(wide.round(3).to_string())
    print(
        f"cooperative: mean RMSE {coop.mean():.3f} m, position NEES <= 6 on "
        f"{int((nees <= 6).sum())} of {len(nees)}, below single on {int((coop < single).sum())} "
        f"of {len(coop)} vehicle-seeds (single mean {single.mean():.3f} m)"
    )
    if baseline is not None:
        ref = wide[("rmse_m", "baseline")]
        ratio, lo, hi, below, n = ratio_ci(coop.to_numpy(float), ref.to_numpy(float))
        ref_nees = wide[("nees", "baseline")]
        print(
            f"against the baseline (overrides {baseline or 'none'}): mean RMSE {ref.mean():.3f} m,"
            f" NEES <= 6 on {int((ref_nees <= 6).sum())} of {len(ref_nees)}; the paired ratio of"
            f" the errors (geometric mean over {n} vehicle-seeds) {ratio:.3f}, 95 % interval"
            f" {lo:.3f}-{hi:.3f}, lower on {round(below * n)} of {n}"
        )
        if lo < 1.0 < hi:
            print("the interval holds 1: these seeds do not tell the two settings apart")
    assert np.isfinite(table[["rmse_m", "nees"]].to_numpy(dtype=float)).all()
    expected = {"cooperative", "single"} | ({"baseline"} if baseline is not None else set())
    assert set(table["mode"]) == expected
