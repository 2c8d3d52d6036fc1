"""`make bench`: `cvslam run` on the paper's two-UAV mission, stage by stage (issue 8).

What `make demo` does after its simulation: `cvslam run uav1.mcap uav2.mcap -o R` with the
default config (extract; fuse cooperative NH-infinity, single and EKF; mosaic; eval). Prints
each stage's wall time from run.yaml, the whole command's wall time and peak memory
(`/usr/bin/time -v`), and then a second `cvslam run` with nothing changed, which must skip
every stage (it only hashes the inputs). Baseline for the ratios, measured in the same run:
`cvslam simulate` of the mission (what a user waits for before `cvslam run`).

Asserted: every stage ran and the report exists; the rerun skips all 6 stages and takes
under a quarter of the first run; the whole `cvslam run` under 5 minutes (the demo's budget
on this 2-core machine, an acceptance figure rather than a speed target).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml

STAGES = ("extract", "fuse", "fuse_single", "fuse_ekf", "mosaic", "eval")


def _timed(*args: object) -> tuple[float, float, str]:
    """(wall s, peak RSS MiB, stderr) of `cvslam ARGS` in a fresh process."""
    cmd = ["/usr/bin/time", "-v", sys.executable, "-m", "cvslam_cli", *map(str, args)]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-2000:]
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr)
    return wall, int(rss.group(1)) / 1024 if rss else float("nan"), r.stderr


@pytest.fixture(scope="module")
def bench_dir():
    tmp = Path(tempfile.mkdtemp(prefix="cvslam_run_bench_"))
    yield tmp
    shutil.rmtree(tmp, ignore_errors=True)


def test_run_stages_rerun_and_demo_budget(bench_dir):
    sim = bench_dir / "sim"
    t_sim, rss_sim, _ = _timed("-q", "simulate", "uav2_paper", "-o", sim)
    logs = [sim / "uav1.mcap", sim / "uav2.mcap"]
    run = bench_dir / "run"
    t_run, rss_run, _ = _timed("run", *logs, "-o", run)
    stages = yaml.safe_load((run / "run.yaml").read_text())["stages"]
    assert set(STAGES) <= set(stages)
    assert (run / "eval" / "report.html").is_file()
    t_again, rss_again, err_again = _timed("run", *logs, "-o", run)
    skipped = err_again.count("up to date")

    rows = [{"stage": s, "wall s": round(stages[s]["wall_s"], 1)} for s in STAGES if s in stages]
    rows += [
        {"stage": "cvslam run (whole command)", "wall s": round(t_run, 1)},
        {"stage": "cvslam run again (nothing changed)", "wall s": round(t_again, 1)},
        {"stage": "baseline: cvslam simulate uav2_paper", "wall s": round(t_sim, 1)},
    ]
    table = pd.DataFrame(rows)
    table["/ simulate"] = (table["wall s"] / t_sim).round(2)
    print()
    print(table.to_string(index=False))
    print(f"peak RSS: run {rss_run:.0f} MiB, rerun {rss_again:.0f} MiB, simulate {rss_sim:.0f} MiB")
    print(pd.read_csv(run / "eval" / "headline.csv", index_col=0).round(2).to_string())
    assert skipped == len(STAGES), err_again[-2000:]
    assert t_again < 0.25 * t_run
    assert t_run < 300.0
