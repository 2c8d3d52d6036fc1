"""`make bench`: the ground robots of `ugv2_yard` with rendered images (issue 6; the paper's
Figure 17): cooperative vs each robot alone vs wheel-odometry dead reckoning.

The whole pipeline as a user runs it: `cvslam simulate ugv2_yard --seed S` (images), `cvslam
extract` on both logs, `cvslam fuse --single` and `cvslam fuse` (cooperative), with the
`fuse.` overrides of the dataset recipe `datasets/ugv2_yard.yaml` (none since the
observability constraint is on by default for wheel odometry: BENCHMARKS.md, "Fuse: ground
robots constrained by default"), or CVSLAM_YARD_SET (";"-separated); odometry motion model,
NH-infinity. Landmark mode is not used here: it has no
occlusion and no change of appearance with the viewing angle, which is what makes forward
cameras hard (two robots driving towards each other see the two sides of the same boxes).

Per seed and robot: position RMSE and final error (cooperative, single, dead reckoning),
loop closures, type-2 observations and the events. Asserted: no divergence; every robot's
RMSE at most half of dead reckoning's (the yard is small: odometry drifts only 4-5 m RMSE),
in both modes; cooperative RMSE not above single (1.05x) for each robot, on each seed (issue
15's goal 3). On 2026-12-07 (with the constraint, seed 2) that last check fails: robot1
0.12 vs 0.09 m, robot2 0.16 vs 0.11 m, though the final errors are lower cooperative (0.08 /
0.15 against 0.16 / 0.20 m); dead reckoning 4.43 and 5.21 m (without the constraint robot2
0.11 vs 0.10 m, robot1 0.70 vs 0.85 m). Two robots that see the yard's walls from opposite
directions share few landmarks (9 type-2 observations for robot1).

Environment: CVSLAM_YARD_SEEDS (default "2", the scenario's own seed; each seed takes about
3 minutes on 2 cores, most of it rendering and extraction), CVSLAM_YARD_SET.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd
import pytest
import yaml

from cvslam_cli.batch.recipe import load_recipe

SEEDS = [int(s) for s in os.environ.get("CVSLAM_YARD_SEEDS", "2").split(",") if s]
ROBOTS = ("robot1", "robot2")
RECIPE = Path(__file__).resolve().parents[2] / "datasets" / "ugv2_yard.yaml"


def _overrides() -> list[str]:
    """CVSLAM_YARD_SET when given, else the recipe's `fuse.` overrides."""
    value = os.environ.get("CVSLAM_YARD_SET")
    if value is not None:
        return [s for s in value.split(";") if s.strip()]
    return [s for s in load_recipe(RECIPE).overrides if s.startswith("fuse.")]


def _cvslam(*args: object) -> None:
    cmd = [sys.executable, "-m", "cvslam_cli", "-q", *map(str, args)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def _summary(run: Path, stage: str) -> dict:
    return yaml.safe_load((run / "run.yaml").read_text())["stages"][stage]["summary"]


@pytest.fixture(scope="module")
def yard_runs() -> dict[int, Path]:
    tmp = Path(tempfile.mkdtemp(prefix="cvslam_yard_"))
    runs = {}
    for seed in SEEDS:
        run = tmp / f"seed{seed}"
        _cvslam("simulate", "ugv2_yard", "-o", run, "--seed", seed)
        _cvslam("extract", *(run / f"{r}.mcap" for r in ROBOTS), "-o", run)
        sets = [a for s in _overrides() for a in ("--set", s)]
        _cvslam("fuse", run, "--single", *sets)
        _cvslam("fuse", run, *sets)
        runs[seed] = run
    return runs


def test_cooperative_ground_robots_are_no_worse_than_alone(yard_runs):
    rows = []
    for seed, run in yard_runs.items():
        coop, single = _summary(run, "fuse"), _summary(run, "fuse_single")
        events = pd.read_csv(run / "fuse" / "events.csv")
        tl = pd.read_csv(run / "fuse" / "timeline.csv")
        for r in ROBOTS:
            c, s = coop["vehicles"][r], single["vehicles"][r]
            cross = events[(events.event == "cross_vehicle") & (events.vehicle == r)]
            rows.append(
                {
                    "seed": seed,
                    "robot": r,
                    "distance m": round(c["distance_m"], 1),
                    "RMSE coop": round(c["rmse_m"], 2),
                    "RMSE single": round(s["rmse_m"], 2),
                    "RMSE dead reckoning": round(c["rmse_deadreckoning_m"], 2),
                    "final coop": round(c["final_error_m"], 2),
                    "final single": round(s["final_error_m"], 2),
                    "final dead reckoning": round(c["final_error_deadreckoning_m"], 2),
                    "loops coop/single": f"{c['loop_closures']}/{s['loop_closures']}",
                    "type-2 obs": int(tl[tl.vehicle == r].type2.sum()),
                    "cross-vehicle events": len(cross),
                    "real time coop": round(coop["realtime_factor"], 1),
                }
            )
    table = pd.DataFrame(rows)
    print(f"\nugv2_yard, images, overrides {_overrides() or 'none'}: cooperative vs single vs "
          "dead reckoning (metres):")  # fmt: skip
    print(table.to_string(index=False))
    for row in rows:
        for mode in ("coop", "single"):
            assert row[f"RMSE {mode}"] < 0.5 * row["RMSE dead reckoning"], row
        assert row["RMSE coop"] <= 1.05 * row["RMSE single"], row
