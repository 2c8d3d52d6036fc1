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

Asserted: every command succeeds (no divergence) and every error is finite; nothing about
accuracy (DESIGN.md convention 8: figures are printed, the issue notes judge them).

Run time: ~2.5 min per seed on the 2-core machine, most of it rendering and extraction;
CVSLAM_IMAGES_SIM names a folder that keeps the simulations and feature files between runs
(the filters are always run again), so that comparing settings costs only the fuses.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "runs" / "benchmarks"


def _cvslam(*args: object) -> None:
    """`cvslam ARGS` in a fresh process; its stderr's end on failure."""
    r = subprocess.run(
        [sys.executable, "-m", "cvslam_cli", "-q", *map(str, args)], capture_output=True, text=True
    )
    assert r.returncode == 0, f"cvslam {' '.join(map(str, args))}: {r.stderr[-2000:]}"


def prepared(base: Path, scenario: str, seed: int) -> tuple[Path, Path]:
    """(sim, run) of one seed under `base`: simulated with images and extracted unless kept
    there already."""
    sim, run = base / f"{scenario}_{seed}" / "sim", base / f"{scenario}_{seed}" / "run"
    if not (sim / "scenario.yaml").is_file():
        _cvslam("simulate", scenario, "-o", sim, "--seed", seed, "--force")
    if not (run / "features").is_dir():
        _cvslam("extract", *sorted(sim.glob("*.mcap")), "-o", run)
    return sim, run


def _seed_run(base: Path, scenario: str, seed: int, sets: list[str]) -> pd.DataFrame:
    """One seed: simulate and extract (unless kept), both fuses, eval; its rows."""
    _, run = prepared(base, scenario, seed)
    overrides = [a for s in sets for a in ("--set", s)]
    _cvslam("fuse", run, "--force", *overrides)
    _cvslam("fuse", run, "--single", "--force", *overrides)
    _cvslam("eval", run, "--force")
    metrics = json.loads((run / "eval" / "metrics.json").read_text())
    rows = []
    for e in metrics["estimates"]:
        mode = e["estimate"].split()[0]  # "cooperative" / "single" / "dead"
        if mode in ("cooperative", "single"):
            rows.append(
                {"seed": seed, "vehicle": e["vehicle"], "mode": mode, "rmse_m": e["ate_rmse_m"],
                 "nees": e["nees_mean"], "in_band": e["nees_in_band"]}
            )  # fmt: skip
    return pd.DataFrame(rows)


def test_images_runs_over_seeds() -> None:
    scenario = os.environ.get("CVSLAM_IMAGES_SCENARIO", "uav2_paper")
    seeds = [int(s) for s in os.environ.get("CVSLAM_IMAGES_SEEDS", "1,2,3,4,5").split(",")]
    sets = [s for s in os.environ.get("CVSLAM_IMAGES_SET", "").split(";") if s.strip()]
    kept = os.environ.get("CVSLAM_IMAGES_SIM")
    with tempfile.TemporaryDirectory(prefix="cvslam_images_seeds_") as tmp:
        base = Path(kept) if kept else Path(tmp)
        table = pd.concat([_seed_run(base, scenario, seed, sets) for seed in seeds])
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
    assert np.isfinite(table[["rmse_m", "nees"]].to_numpy(dtype=float)).all()
    assert set(table["mode"]) == {"cooperative", "single"}
