"""`make bench`: four short recipes, serially vs `make -j2 batch` vs `cvslam batch` on a local
Dask cluster of 2 workers (issue 17).

Each recipe simulates 6 s of two small UAVs (376 x 240 images, seeds 1-4) and runs every stage
(extract, fuse cooperative NH-infinity and EKF, mosaic, eval); each mode starts from nothing
(no logs, no runs). Baseline, measured in the same run: the serial batch (`cvslam batch
--serial`, one recipe after another in one process). Printed: each mode's wall time and its
speed-up over the serial one (2 cores: at most 2x; what is left is the start of the worker
processes or of the cluster, and the recipes' unequal lengths), and the CPU seconds of all
its processes (CPU / wall: the cores it kept busy; on a machine shared with other work the
wall times say little without it). Asserted: every mode made
every report, and the cluster's feature files equal the serial run's byte for byte.
"""

from __future__ import annotations

import filecmp
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import yaml

from tests.scenarios import small_uav_scenario

REPO = Path(__file__).resolve().parent.parent.parent
NAMES = [f"short_{k}" for k in range(1, 5)]
CAMERA = {"width": 376, "height": 240, "fx": 225.0, "fy": 225.0, "cx": 187.5, "cy": 119.5}


@pytest.fixture(scope="module")
def project():
    root = Path(tempfile.mkdtemp(prefix="cvslam_batch_bench_"))
    (root / "scenario").mkdir()
    small_uav_scenario(
        root / "scenario",
        duration_s=6.0,
        **{f"vehicles.{v}.camera.{k}": x for v in ("uav1", "uav2") for k, x in CAMERA.items()},
        **{"terrain.texture_px_per_m": 4.0},
    )
    (root / "datasets").mkdir()
    for k, name in enumerate(NAMES, start=1):
        recipe = {
            "logs": [{"simulate": "../scenario/small.yaml", "seed": k}],
            "comparisons": ["ekf"],
        }
        (root / "datasets" / f"{name}.yaml").write_text(yaml.safe_dump(recipe))
    yield root
    shutil.rmtree(root, ignore_errors=True)


def _clean(root: Path) -> None:
    for folder in ("runs", "generated"):
        shutil.rmtree(root / folder, ignore_errors=True)


def _timed(cmd: list[str]) -> tuple[float, float]:
    """(wall s, CPU s of the command and every process it started) of `cmd`."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _reports(root: Path) -> bool:
    return all((root / "runs" / n / "eval" / "report.html").is_file() for n in NAMES)


def test_batch_serial_vs_make_j2_vs_dask_two_workers(project):
    recipes = [str(project / "datasets" / f"{n}.yaml") for n in NAMES]
    cvslam = [sys.executable, "-m", "cvslam_cli"]
    dirs = ["--runs", str(project / "runs"), "--generated", str(project / "generated")]
    walls = {}
    _clean(project)
    walls["serial (cvslam batch --serial)"] = _timed(
        [*cvslam, "batch", "--serial", *recipes, *dirs]
    )
    assert _reports(project)
    shutil.move(project / "runs", project / "runs_serial")
    _clean(project)
    make = ["make", "-C", str(REPO), "-j2", "batch", f"DATASETS_DIR={project / 'datasets'}",
            f"RUNS_DIR={project / 'runs'}", f"GENERATED_DIR={project / 'generated'}",
            f"CVSLAM={sys.executable} -m cvslam_cli", "INSTALL="]  # fmt: skip
    walls["make -j2 batch"] = _timed(make)
    assert _reports(project)
    _clean(project)
    walls["cvslam batch --local-workers 2"] = _timed(
        [*cvslam, "batch", "--local-workers", "2", *recipes, *dirs]
    )
    assert _reports(project)
    for n in NAMES:
        for v in ("uav1", "uav2"):
            a = project / "runs_serial" / n / "features" / f"{v}.npz"
            assert filecmp.cmp(a, project / "runs" / n / "features" / f"{v}.npz", shallow=False)
    base = walls["serial (cvslam batch --serial)"][0]
    print(f"\nbatch of {len(NAMES)} recipes (load average after: {os.getloadavg()[0]:.1f}):")
    for mode, (wall, cpu) in walls.items():
        print(
            f"  {mode:34s} {wall:6.1f} s wall  {cpu:6.1f} s CPU ({cpu / wall:.2f} cores)"
            f"   speed-up {base / wall:.2f}x"
        )
