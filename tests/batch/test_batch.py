"""Batch runs end to end on two tiny simulated recipes: `make -j2 batch`, `cvslam batch` on a
local Dask cluster (byte-identical to the serial run, a failing recipe reported while the
others finish), the summary, a moved run directory, distributed extract, a sweep."""

from __future__ import annotations

import filecmp
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from cvslam_cli.io.rundir import content_sha256
from tests.scenarios import small_uav_scenario

REPO = Path(__file__).resolve().parent.parent.parent
TINY = ("tiny_a", "tiny_b")
# files whose content varies from run to run (times, timing columns; io/rundir.py)
VOLATILE = {"run.yaml", "report.html", "cvslam.log", ".lock"}


def _recipe(folder: Path, name: str, seed: int, *, lean: bool = False) -> Path:
    """A recipe of 3 s of two small UAVs; `lean`: no comparison, no mosaic (same logs)."""
    path = folder / f"{name}.yaml"
    recipe = {
        "description": f"3 s of two small UAVs, seed {seed}",
        "logs": [{"simulate": "../scenario/small.yaml", "seed": seed}],
        "comparisons": [] if lean else ["ekf"],
    }
    if lean:
        recipe["mosaic"] = False
    path.write_text(yaml.safe_dump(recipe))
    return path


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    """A project folder: `datasets/` with two tiny recipes, `lean/` with the same two without
    comparisons and mosaics (for sweeps and searches), `broken/` with one whose log is not an
    MCAP file, `scenario/small.yaml` (3 s)."""
    root = tmp_path_factory.mktemp("project")
    (root / "scenario").mkdir()
    small_uav_scenario(root / "scenario", duration_s=3.0)
    (root / "datasets").mkdir()
    (root / "lean").mkdir()
    for k, name in enumerate(TINY):
        _recipe(root / "datasets", name, k + 1)
        _recipe(root / "lean", name, k + 1, lean=True)
    (root / "broken").mkdir()
    (root / "broken" / "corrupt.mcap").write_bytes(b"recorded by nothing: not MCAP\n" * 4)
    (root / "broken" / "bad.yaml").write_text(yaml.safe_dump({"logs": [{"file": "corrupt.mcap"}]}))
    return root


def _make(project: Path, *targets: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [
            "make",
            "-C",
            str(REPO),
            *targets,
            f"DATASETS_DIR={project / 'datasets'}",
            f"RUNS_DIR={project / 'runs'}",
            f"GENERATED_DIR={project / 'generated'}",
            f"CVSLAM={sys.executable} -m cvslam_cli",
            "INSTALL=",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )


@pytest.fixture(scope="module")
def made(project: Path) -> Path:
    """`make -j2 batch` on the tiny recipes (each recipe `cvslam batch --serial`)."""
    res = _make(project, "-j2", "batch")
    assert res.returncode == 0, res.stdout + res.stderr
    return project


def _finished(run: Path) -> dict[str, str]:
    stages = yaml.safe_load((run / "run.yaml").read_text())["stages"]
    return {k: v["finished"] for k, v in stages.items()}


def test_make_j2_batch_builds_every_recipe_and_a_second_make_does_nothing(made):
    for name in TINY:
        run = made / "runs" / name
        assert (run / "eval" / "report.html").is_file()
        assert set(_finished(run)) == {"extract", "fuse", "fuse_ekf", "mosaic", "eval"}
        assert "START batch" in (run / "cvslam.log").read_text()  # the run's own log
        metrics = pd.read_csv(run / "eval" / "metrics.csv")
        assert set(metrics["dataset"]) == {name} and set(metrics["run_dir"]) == {name}
    assert _make(made, "-q", "batch").returncode == 0  # up to date: nothing to do
    res = _make(made, "-n", "batch")
    assert res.returncode == 0 and "cvslam" not in res.stdout
    # a changed recipe is rebuilt by make, and its stages skip what is up to date
    before = _finished(made / "runs" / "tiny_a")
    os.utime(made / "datasets" / "tiny_a.yaml")
    res = _make(made, "batch")
    assert res.returncode == 0, res.stderr
    assert res.stdout.count("batch --serial") == 1
    assert _finished(made / "runs" / "tiny_a") == before


def test_summary_has_one_row_per_run_vehicle_and_estimate_equal_to_metrics(made):
    res = _make(made, "summary")
    assert res.returncode == 0, res.stderr
    summary = pd.read_csv(made / "runs" / "summary.csv")
    metrics = {n: pd.read_csv(made / "runs" / n / "eval" / "metrics.csv") for n in TINY}
    assert len(summary) == sum(len(m) for m in metrics.values()) == 2 * 2 * 3  # runs x uavs x est.
    assert not summary.duplicated(["run_dir", "vehicle", "estimate"]).any()
    for name, m in metrics.items():
        rows = summary[summary["run_dir"] == name].reset_index(drop=True)
        pd.testing.assert_frame_equal(rows[list(m.columns)], m, check_exact=True)
        fuse_rows = rows[rows["run"] == "fuse"]
        stages = yaml.safe_load((made / "runs" / name / "run.yaml").read_text())["stages"]
        assert (fuse_rows["fuse_wall_s"] == stages["fuse"]["wall_s"]).all()
        assert (fuse_rows["realtime_factor"] == stages["fuse"]["summary"]["realtime_factor"]).all()
    page = (made / "runs" / "summary.html").read_text()
    assert page.count("data:image/png;base64,") == 1
    assert 'href="tiny_a/eval/report.html"' in page and 'href="tiny_b/eval/report.html"' in page


def test_a_moved_run_directory_is_still_up_to_date(made, tmp_path, cvslam):
    moved = tmp_path / "moved"
    for folder in ("runs", "generated"):
        shutil.copytree(made / folder / "tiny_a", moved / folder / "tiny_a")
    before = _finished(moved / "runs" / "tiny_a")
    res = cvslam(
        "batch", "--serial", made / "datasets" / "tiny_a.yaml",
        "--runs", moved / "runs", "--generated", moved / "generated",
    )  # fmt: skip
    assert res.code == 0, res.err
    assert _finished(moved / "runs" / "tiny_a") == before
    log = (moved / "runs" / "tiny_a" / "cvslam.log").read_text()
    assert log.count("is up to date") >= 6  # the simulated logs and the 5 stages


def _strip_times(text: str) -> str:
    return re.sub(r"\d{4}-\d\d-\d\d[T ]\d\d:\d\d:\d\d ?[+-]\d{4}", "<time>", text)


def _compare_trees(a: Path, b: Path) -> list[str]:
    """The files that differ between two output trees, timing columns and times aside."""
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b
    differ = []
    for rel in files_a:
        pa, pb = a / rel, b / rel
        if rel.name in VOLATILE:
            if rel.name == "report.html" and _strip_times(pa.read_text()) != _strip_times(
                pb.read_text()
            ):
                differ.append(str(rel))
            continue
        same = (
            content_sha256(pa) == content_sha256(pb)
            if rel.suffix == ".csv"
            else filecmp.cmp(pa, pb, shallow=False)
        )
        if not same:
            differ.append(str(rel))
    return differ


def test_batch_on_a_local_dask_cluster_equals_the_serial_run_and_reports_a_failure(made, cvslam):
    # the serial (make) outputs moved aside; the cluster's are made at the same paths
    ref = made / "reference"
    ref.mkdir()
    for folder in ("runs", "generated"):
        (made / folder).rename(ref / folder)
    try:
        res = cvslam(
            "batch", *(made / "datasets" / f"{n}.yaml" for n in TINY), made / "broken" / "bad.yaml",
            "--local-workers", 2, "--runs", made / "runs", "--generated", made / "generated",
        )  # fmt: skip
        assert res.code == 1
        assert re.search(r"\[\d/3\] bad failed: .*corrupt\.mcap", res.err), res.err
        assert "1 of 3 recipe(s) failed: bad" in res.err.strip().splitlines()[-1]
        for name in TINY:
            assert re.search(rf"\[\d/3\] {name}: done", res.err), res.err
            assert _compare_trees(ref / "runs" / name, made / "runs" / name) == []
            assert _compare_trees(ref / "generated" / name, made / "generated" / name) == []
    finally:
        for folder in ("runs", "generated"):
            shutil.rmtree(made / folder, ignore_errors=True)
            (ref / folder).rename(made / folder)


def test_distributed_extract_equals_local_extract(made, tmp_path, cvslam):
    from distributed import LocalCluster

    logs = sorted((made / "generated" / "tiny_a" / "sim").glob("*.mcap"))
    assert cvslam("-q", "extract", *logs, "-o", tmp_path / "local", "--workers", 1).code == 0
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as local:
        res = cvslam(
            "-q", "extract", *logs, "-o", tmp_path / "dask", "--scheduler", local.scheduler_address
        )
    assert res.code == 0, res.err
    for v in ("uav1", "uav2"):
        a, b = tmp_path / "local" / "features", tmp_path / "dask" / "features"
        assert filecmp.cmp(a / f"{v}.npz", b / f"{v}.npz", shallow=False)
        assert content_sha256(a / f"{v}_stats.csv") == content_sha256(b / f"{v}_stats.csv")


def test_sweep_runs_every_grid_point_and_writes_the_summary(made, tmp_path, cvslam):
    res = cvslam(
        "sweep", made / "lean" / "tiny_b.yaml", "--grid", "eval.align=none,se3", "--serial",
        "--runs", tmp_path / "runs", "--generated", made / "generated",
    )  # fmt: skip
    assert res.code == 0, res.err
    assert "sim is up to date" in res.err  # the logs of datasets/tiny_b.yaml, shared
    points = ["tiny_b__eval.align=none", "tiny_b__eval.align=se3"]
    assert sorted(p.name for p in (tmp_path / "runs").iterdir() if p.is_dir()) == points
    summary = pd.read_csv(tmp_path / "runs" / "tiny_b_sweep.csv")
    assert sorted(set(summary["run_dir"])) == points and set(summary["dataset"]) == {"tiny_b"}
    ate = summary.pivot_table(index=["vehicle", "estimate"], columns="run_dir", values="ate_rmse_m")
    assert (ate[points[1]] <= ate[points[0]] + 1e-12).all()  # aligning can only lower the ATE
    # the points' run.yaml record their override
    for point, align in zip(points, ("none", "se3"), strict=True):
        cfg = yaml.safe_load((tmp_path / "runs" / point / "run.yaml").read_text())["config"]
        assert cfg["eval"]["align"] == align


def test_summary_of_a_run_without_eval_is_one_line(tmp_path, cvslam):
    (tmp_path / "r").mkdir()
    res = cvslam("summary", tmp_path / "r", "-o", tmp_path / "s")
    assert res.code == 1 and len(res.err.strip().splitlines()) == 1
    assert "r/eval/metrics.csv: not found; run `cvslam eval" in res.err
    assert not (tmp_path / "s.csv").exists()


def test_batch_options_are_exclusive_and_recipes_checked_first(project, cvslam):
    res = cvslam("batch", project / "datasets" / "tiny_a.yaml", "--serial", "--local-workers", 2)
    assert res.code == 2 and "at most one of --scheduler, --local-workers, --serial" in res.err
    bad = project / "broken" / "unknown.yaml"
    bad.write_text("logs: [{file: x.mcap}]\nvehicle: uav1\n")
    res = cvslam("batch", project / "datasets" / "tiny_a.yaml", bad, "--serial")
    assert res.code == 1 and f"{bad}: vehicle: unknown key" in res.err
    assert not (project / "runs" / "unknown").exists()


def test_tune_searches_and_records_each_trial(made, tmp_path, cvslam):
    res = cvslam(
        "tune", made / "lean" / "tiny_a.yaml", "--param", "fuse.hinf.gamma=3:100:log",
        "--trials", 2, "--serial", "--runs", tmp_path / "runs", "--generated", made / "generated",
        "-o", tmp_path / "study",
    )  # fmt: skip
    assert res.code == 0, res.err
    trials = pd.read_csv(tmp_path / "study_trials.csv")
    assert list(trials["trial"]) == [0, 1] and set(trials["state"]) == {"complete"}
    assert trials["fuse.hinf.gamma"].between(3, 100).all()
    for row in trials.itertuples(index=False):
        run = tmp_path / "runs" / f"tiny_a__trial{row.trial:03d}"
        cfg = yaml.safe_load((run / "run.yaml").read_text())["config"]
        assert cfg["fuse"]["hinf"]["gamma"] == row._1  # the trial's value, as run
        m = pd.read_csv(run / "eval" / "metrics.csv")
        coop = m.loc[m["estimate"] == "cooperative NH-inf", "ate_rmse_m"]
        assert row.mean_ate_rmse_m == pytest.approx(coop.mean(), rel=1e-12)
    best = trials.loc[trials["mean_ate_rmse_m"].idxmin()]
    assert f"best: fuse.hinf.gamma={best['fuse.hinf.gamma']:.6g}" in res.out
    assert len(pd.read_csv(tmp_path / "study.csv")) == 2 * 2 * 2  # trials x uavs x estimates
