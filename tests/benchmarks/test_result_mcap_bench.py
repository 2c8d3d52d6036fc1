"""`make bench`: result.mcap (issue 19): its size and write time for a long run, and the
NumPy Path encoding against the generic encoder of mcap-ros2-support, in the same run.

- Path encoding: a 1000-pose nav_msgs/Path by `path_cdr` vs `serialize_dynamic` on the
  fields (what `LogWriter.write` does); the bytes are the same (tests/io/test_mcap_writer.py).
- File: two vehicles at 20 Hz for 120 s and 600 s, dead reckoning and 100 Hz ground truth
  (six growing paths), 10 landmarks a second, random poses (the least compressible case):
  size (bounded by `ResultDecimation`) and write time, against writing the per-pose
  messages only (the floor: one PoseWithCovarianceStamped and one /tf per estimate).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from mcap_ros2._dynamic import serialize_dynamic

from cvslam_cli.io.mcap_writer import path_cdr, path_fields
from cvslam_cli.io.result_mcap import write_result_mcap
from cvslam_cli.io.ros2_msgdefs import msgdef_text
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.poses import PoseTable


def _table(n: int, dt_ns: int, seed: int) -> PoseTable:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return PoseTable(np.arange(n, dtype=np.int64) * dt_ns, np.cumsum(rng.normal(size=(n, 3)), 0), q)


def _landmarks(n: int, span_ns: int) -> LandmarkMap:
    rng = np.random.default_rng(3)
    first = np.sort(rng.integers(0, span_ns, n))
    return LandmarkMap(
        np.arange(n), rng.normal(scale=100, size=(n, 3)), np.full((n, 3), 0.1), ("uav1",) * n,
        np.ones(n, int), first, first + 1, np.ones(n, bool), np.full(n, -1),
    )  # fmt: skip


def _best_of(k: int, fn) -> float:
    times = []
    for _ in range(k):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def test_path_encoding_speed():
    encode = serialize_dynamic("nav_msgs/msg/Path", msgdef_text("nav_msgs/msg/Path"))[
        "nav_msgs/msg/Path"
    ]
    t = _table(1000, 50_000_000, 0)
    args = (t.stamps_ns, t.p_nav_m, t.q_nav_body_xyzw)
    fast = _best_of(5, lambda: path_cdr(10**9, "nav", *args))
    generic = _best_of(3, lambda: encode(path_fields(10**9, *args, "nav")))
    print(f"\n1000-pose Path: path_cdr {fast * 1e3:.2f} ms, generic {generic * 1e3:.1f} ms, "
          f"speed-up {generic / fast:.0f}x")  # fmt: skip
    assert generic / fast > 5


def _write(path: Path, duration_s: int, poses_only: bool) -> tuple[float, float]:
    """(seconds, MB) writing result.mcap of the synthetic run of `duration_s`."""
    n = duration_s * 20
    est = {v: _table(n, 50_000_000, k) for k, v in enumerate(("uav1", "uav2"))}
    cov = {v: np.tile(np.eye(6), (n, 1, 1)) for v in est}
    if poses_only:
        extra = {}
        lm = _landmarks(0, 1)
    else:
        gt = {v: _table(duration_s * 100, 10_000_000, 10 + k) for k, v in enumerate(est)}
        extra = {"deadreckoning": est, "ground_truth": gt}
        lm = _landmarks(duration_s * 10, duration_s * 10**9)
    t0 = time.perf_counter()
    write_result_mcap(path, est, lm, pose_covariances=cov, **extra)
    return time.perf_counter() - t0, path.stat().st_size / 1e6


def test_result_mcap_size_and_write_time(tmp_path: Path):
    for duration_s in (120, 600):
        floor_s, floor_mb = _write(tmp_path / "floor.mcap", duration_s, poses_only=True)
        full_s, mb = _write(tmp_path / "full.mcap", duration_s, poses_only=False)
        print(
            f"{duration_s} s: {mb:.1f} MB ({floor_mb:.1f} MB poses only), {full_s:.1f} s "
            f"({floor_s:.1f} s poses only, ratio {full_s / floor_s:.2f})"
        )
        assert mb < 200
