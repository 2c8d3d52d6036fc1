"""Worker pools: order kept, a killed worker fails the stage at once naming the job, Ctrl-C and
SIGTERM end cleanly (exit 130 / 143, no traceback, no leaked semaphore)."""

from __future__ import annotations

import multiprocessing.connection
import os
import re
import signal
import subprocess
import sys
import time
from typing import Any

import psutil
import pytest

from cvslam_cli.parallel import STATE, WorkerError, ordered_map
from tests.conftest import REPO
from tests.signals import default_sigint
from tests.synth import write_stereo_log


def _square_plus(job: int) -> int:
    return job * job + STATE["add"]


def _die_at(job: int) -> int:
    if job == STATE["die_at"]:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.01)
    return job


def test_results_in_order_with_state_in_workers():
    jobs = list(range(37))
    out = list(ordered_map(_square_plus, jobs, workers=2, state={"add": 3}))
    assert out == [j * j + 3 for j in jobs]
    assert list(ordered_map(_square_plus, jobs, workers=1, state={"add": 3})) == out


def test_killed_worker_fails_within_seconds_naming_the_job():
    t0 = time.monotonic()
    got = []
    with pytest.raises(WorkerError, match=r"worker process died .* job (\d+) or a job") as exc:
        for r in ordered_map(
            _die_at, range(200), workers=2, state={"die_at": 12}, describe=lambda j: f"job {j}"
        ):
            got.append(r)
    assert time.monotonic() - t0 < 30  # (spawning included) never a hang
    # the job named is the first unfinished one: the killed one or one in flight beside it
    named = int(re.search(r"job (\d+)", str(exc.value)).group(1))
    assert got == list(range(named)) and 12 - 2 * 4 <= named <= 12


def _long_or_die(job: int) -> int:
    if job == 0:
        time.sleep(60)  # the other worker is in the middle of a long job
    else:
        time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGKILL)
    return job


def test_killed_worker_fails_at_once_while_another_is_busy():
    """No other result is coming, so the death must be seen by the map's own watch (the pool
    can miss a worker it started on demand), and the busy worker, which ignores the pool's
    SIGTERM, is killed: the stage ends at once rather than when (or if) its job ends."""
    t0 = time.monotonic()
    with pytest.raises(WorkerError, match="job 0"):
        list(ordered_map(_long_or_die, [0, 1], workers=2, state={}, describe=lambda j: f"job {j}"))
    assert time.monotonic() - t0 < 30


def _die_while_sending(job: int) -> bytes | int:
    """Job 0's worker dies part-way through sending its result to the pool: its pipe writes
    are patched to send the first MiB and then SIGKILL the process. The other job is long."""
    if job != 0:
        time.sleep(60)
        return job
    send = multiprocessing.connection.Connection._send  # type: ignore[attr-defined]

    def send_part_then_die(self: Any, buf: Any, write: Any = os.write) -> None:
        if len(buf) > 1 << 20:
            write(self._handle, bytes(memoryview(buf)[: 1 << 20]))
            os.kill(os.getpid(), signal.SIGKILL)
        send(self, buf, write)

    multiprocessing.connection.Connection._send = send_part_then_die  # type: ignore[attr-defined]
    return bytes(4 << 20)


def test_worker_killed_while_sending_its_result_fails_at_once():
    """A worker that dies half-way through a result leaves the pool's manager thread reading
    the rest of that message: the pool's write end of the result pipe, held open in this
    process too, must be closed for the read to end (it hung the stage's clean-up before).
    Run in a subprocess: a hang here must fail the test, not stall the suite."""
    code = (
        "from cvslam_cli.parallel import WorkerError, ordered_map\n"
        "from tests.test_parallel import _die_while_sending\n"
        "try:\n"
        "    list(ordered_map(_die_while_sending, [0, 1], workers=2,\n"
        "                     state={}, describe=lambda j: f'job {j}'))\n"
        "except WorkerError as e:\n"
        "    print(e)\n"
    )
    t0 = time.monotonic()
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
        env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "worker process died" in out.stdout and "job 0" in out.stdout, out
    assert "leaked" not in out.stderr, out.stderr
    assert time.monotonic() - t0 < 30


@pytest.fixture
def busy_extract(tmp_path):
    """A `cvslam extract --workers 2` subprocess, returned once both workers are running."""
    synth = write_stereo_log(tmp_path / "a.mcap", n_frames=400, size=(320, 240), rate_hz=20)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cvslam_cli",
            "extract",
            str(synth.path),
            "-o",
            str(tmp_path / "run"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,  # its own process group, as a shell gives a job
        preexec_fn=default_sigint,
    )
    parent = psutil.Process(proc.pid)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(parent.children()) < 2:
        time.sleep(0.2)
    time.sleep(1.5)  # the workers are past spawning, in the middle of frames
    assert proc.poll() is None, proc.communicate()
    yield proc, tmp_path / "run"
    if proc.poll() is None:
        proc.kill()
        proc.wait()


@pytest.mark.parametrize(("sig", "code", "group"), [("SIGINT", 130, True), ("SIGTERM", 143, False)])
def test_interrupted_extract_exits_cleanly(busy_extract, sig, code, group):
    proc, run = busy_extract
    workers = psutil.Process(proc.pid).children(recursive=True)
    if group:  # Ctrl-C in a terminal signals the whole foreground group
        os.killpg(proc.pid, getattr(signal, sig))
    else:
        proc.send_signal(getattr(signal, sig))
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert "Traceback" not in err and "leaked" not in err, err
    assert err.strip().splitlines()[-1] in ("cvslam: interrupted", "cvslam: terminated")
    psutil.wait_procs(workers, timeout=10)
    assert not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in workers)
    assert not list(run.glob("features/*.npz"))  # nothing that looks finished


def test_killed_extract_worker_fails_the_stage_naming_the_frame(busy_extract):
    proc, run = busy_extract
    victim = [
        p
        for p in psutil.Process(proc.pid).children()
        if "resource_tracker" not in " ".join(p.cmdline())
    ][-1]
    victim.kill()
    t0 = time.monotonic()
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - t0 < 30
    assert proc.returncode == 1, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("cvslam: error: a worker process died") and "frame at stamp" in last
    assert "Traceback" not in err and "leaked" not in err
    assert not list(run.glob("features/*.npz"))
