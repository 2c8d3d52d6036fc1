"""The run directory's records (`io/rundir.py`): relative paths, content checksums, the
record invalidated before outputs are replaced, one process at a time, the run's log."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from cvslam_cli.config import load_config
from cvslam_cli.errors import CvslamError
from cvslam_cli.io.rundir import TIMING_COLUMNS, RunDir, content_sha256, file_sha256

REPO = Path(__file__).resolve().parent.parent.parent


def _stage(rd: RunDir, inputs: list[Path], outputs: list[Path], cfg=None, force=False) -> str:
    """Plan the stage `demo`; when it is to run, write its outputs and record it."""
    cfg = cfg or load_config()
    plan = rd.plan("demo", cfg, ("eval",), inputs, outputs, force)
    if plan.action == "run":
        for out in outputs:
            out.write_text("made\n")
        rd.record("demo", plan, outputs, {}, 0.1)
    return plan.reason


@pytest.fixture
def setup(tmp_path):
    root = tmp_path / "root"
    (root / "logs").mkdir(parents=True)
    log = root / "logs" / "a.bin"
    log.write_bytes(b"log bytes")
    run = root / "run"
    run.mkdir()
    return root, log, run


def test_paths_recorded_relative_and_a_moved_run_is_up_to_date(setup, tmp_path):
    root, log, run = setup
    out = run / "out.txt"
    assert _stage(RunDir(run), [log], [out]) == "not run yet"
    record = yaml.safe_load((run / "run.yaml").read_text())["stages"]["demo"]
    assert record["inputs"][0]["path"] == "../logs/a.bin"
    assert record["inputs"][0]["sha256"] == file_sha256(log)
    moved = tmp_path / "elsewhere" / "root"
    shutil.move(root, moved)
    moved_log, moved_run = moved / "logs" / "a.bin", moved / "run"
    assert _stage(RunDir(moved_run), [moved_log], [moved_run / "out.txt"]) == "up to date"
    moved_log.write_bytes(b"other bytes")
    assert _stage(RunDir(moved_run), [moved_log], [moved_run / "out.txt"]) == "inputs changed"


def test_timing_columns_do_not_change_the_checksum(tmp_path):
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    a.write_text("stamp_ns,x_m,ms\n1,0.5,3.25\n2,0.6,4.0\n")
    b.write_text("stamp_ns,x_m,ms\n1,0.5,9.75\n2,0.6,1.5\n")  # other timings
    c.write_text("stamp_ns,x_m,ms\n1,0.5,3.25\n2,0.7,4.0\n")  # another result
    assert content_sha256(a) == content_sha256(b) != content_sha256(c)
    assert file_sha256(a) != file_sha256(b)
    stats = tmp_path / "v_stats.csv"
    stats.write_text("stamp_ns,points,t_total_s\n1,5,0.1\n")
    stats2 = tmp_path / "w_stats.csv"
    stats2.write_text("stamp_ns,points,t_total_s\n1,5,0.2\n")
    assert content_sha256(stats) == content_sha256(stats2)
    assert {"ms", "t_total_s"} <= TIMING_COLUMNS
    plain = tmp_path / "map.csv"  # no timing column: the bytes
    plain.write_text("id,x_m\n1,2.0\n")
    assert content_sha256(plain) == file_sha256(plain)


def test_an_interrupted_forced_run_is_never_up_to_date(setup):
    _, log, run = setup
    out = run / "out.txt"
    rd = RunDir(run)
    _stage(rd, [log], [out])
    new = load_config(overrides=["eval.align=se3"])
    plan = rd.plan("demo", new, ("eval",), [log], [out], True)  # --force with another config
    assert plan.action == "run"
    out.write_text("half made with the new config\n")  # ... and interrupted before record()
    record = rd.load()["stages"]["demo"]
    assert record["status"] == "running" and record["config"]["eval"]["align"] == "se3"
    # the next plain run with the new config redoes it; with the old one it is refused
    assert rd.plan("demo", new, ("eval",), [log], [out], False).action == "run"
    with pytest.raises(CvslamError, match=r"different config \(eval\.align: 'se3' -> 'none'\)"):
        rd.plan("demo", load_config(), ("eval",), [log], [out], False)


_HOLD = """
import sys
from pathlib import Path
from cvslam_cli.io.rundir import RunDir
with RunDir(Path(sys.argv[1])).session("holder"):
    print("held", flush=True)
    sys.stdin.readline()
"""


def test_a_second_process_on_a_run_directory_gets_one_line(setup, cvslam):
    _, _, run = setup
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD, str(run)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        res = cvslam("eval", run)
        assert res.code == 1
        lines = res.err.strip().splitlines()
        assert len(lines) == 1, res.err
        assert f"{run}: another cvslam process (pid {holder.pid} on " in lines[0]
        assert "is working on this run directory" in lines[0]
    finally:
        holder.communicate("\n", timeout=30)
    # released: the same command now gets past the lock (to its own error: no fuse run)
    res = cvslam("eval", run)
    assert res.code == 1 and "another cvslam process" not in res.err


def test_the_session_is_reentrant_and_writes_the_run_log(setup):
    _, _, run = setup
    import logging

    log = logging.getLogger("cvslam")
    old_level = log.level
    log.setLevel(logging.INFO)
    try:
        with RunDir(run).session("outer"), RunDir(run).session("inner"):
            log.info("a line of the run")
        with pytest.raises(CvslamError), RunDir(run).session("failing"):
            raise CvslamError("what went wrong")
    finally:
        log.setLevel(old_level)
    text = (run / "cvslam.log").read_text()
    assert text.count("START outer") == 1 and "START inner" not in text
    assert "INFO a line of the run" in text and "END outer: done" in text
    assert "ERROR what went wrong" in text and "END failing: failed" in text
