"""The same scenario, config and seed give byte-identical outputs at another path and with
another worker count; only the documented timing columns and files differ (README,
"Reproducible outputs, bad input")."""

from __future__ import annotations

import csv

import pytest

from tests.scenarios import small_uav_scenario

# what records time (README): these columns, and these files as a whole
TIMING_COLUMNS = {
    "features/uav1_stats.csv": {"t_detect_s", "t_describe_s", "t_match_s", "t_triangulate_s",
                                "t_total_s"},
    "features/uav2_stats.csv": {"t_detect_s", "t_describe_s", "t_match_s", "t_triangulate_s",
                                "t_total_s"},
    "fuse/timeline.csv": {"ms"},
}  # fmt: skip
TIMED_FILES = {"run.yaml", "eval/report.html", "cvslam.log", ".lock"}


def _pipeline(root, workers, cvslam):
    root.mkdir(parents=True)
    sc = small_uav_scenario(root, duration_s=2.5, mode="images")
    run = root / "run"
    steps = (
        lambda: ["simulate", sc, "-o", run, "--workers", workers],
        lambda: ["extract", *sorted(run.glob("*.mcap")), "-o", run, "--workers", workers],
        lambda: ["fuse", run],
        lambda: ["mosaic", run],
        lambda: ["eval", run],
    )
    for step in steps:  # each step's arguments made when it runs (the logs come from simulate)
        res = cvslam("-q", *step())
        assert res.code == 0, res.err
    return run


def _rows_without(path, columns):
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return [{k: v for k, v in r.items() if k not in columns} for r in rows]


@pytest.mark.parametrize("workers", [(1, 2)])
def test_outputs_are_byte_identical_at_another_path_and_worker_count(tmp_path, cvslam, workers):
    a = _pipeline(tmp_path / "a", workers[0], cvslam)
    b = _pipeline(tmp_path / "elsewhere" / "deeper" / "b", workers[1], cvslam)
    files_a = {str(p.relative_to(a)) for p in a.rglob("*") if p.is_file()}
    files_b = {str(p.relative_to(b)) for p in b.rglob("*") if p.is_file()}
    assert files_a == files_b
    assert {"fuse/uav1.tum", "fuse/result.mcap", "features/uav1.npz", "mosaic/all.png"} <= files_a
    for rel in sorted(files_a - TIMED_FILES):
        xa, xb = (a / rel).read_bytes(), (b / rel).read_bytes()
        assert str(a).encode() not in xa, f"{rel} holds the run's path"
        if rel in TIMING_COLUMNS:
            assert _rows_without(a / rel, TIMING_COLUMNS[rel]) == _rows_without(
                b / rel, TIMING_COLUMNS[rel]
            ), rel
        else:
            assert xa == xb, f"{rel} differs"
