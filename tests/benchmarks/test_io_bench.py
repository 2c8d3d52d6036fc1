"""`make bench`: log decoding throughput and memory against baselines run in the same process.

- Throughput: 752x480 mono8 stereo images decoded into records by `LogSet.records()`
  (MCAP chunk decompression + CDR decoding + pairing + reordering) vs the bare `mcap` reader
  iterating the same messages without decoding them (the floor any reader pays).
  Target: >= 500 images/s.
- Memory: peak RSS of a process reading a short log vs one reading a 10x longer log, each
  measured after importing everything (the baseline is an empty read). Must stay flat.
- Per storage (issue 18): the same logs converted by `rosbags-convert`'s converter into a
  rosbag2 MCAP folder, a sqlite3 .db3 bag, a ROS 1 .bag and a zstd file-compressed MCAP, read
  through `open_logs` (the `rosbags` readers, or decompression then the fast path): images/s
  against the bare .mcap fast path of the same run, and peak RSS short vs 10x long.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from cvslam_cli.config import load_config
from cvslam_cli.io.logs import LogSet, open_logs
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.mcap_writer import LogWriter
from cvslam_cli.records.log import StereoFrame
from tests.synth import camera

W, H = 752, 480


def write_log(path: Path, n_pairs: int, seed: int = 0) -> Path:
    """A EuRoC-sized stereo log: blurred texture + per-frame sensor noise, 20 Hz, 200 Hz IMU."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (2 * H, 2 * W), np.uint8), (0, 0), 1.5)
    cams = {
        s: camera(
            W, H, 458.0, right=s == "right", baseline_m=0.11, frame_id=f"uav1/{s}_camera_optical"
        )
        for s in ("left", "right")
    }
    with LogWriter(path) as log:
        for i in range(n_pairs):
            stamp = 10**9 + i * 50_000_000
            for j in range(10):
                log.write_imu(
                    "/uav1/imu",
                    stamp + j * 5_000_000,
                    rng.normal(size=3),
                    rng.normal(size=3),
                    "uav1/base_link",
                )
            for side, cam in cams.items():
                x, y = (7 * i + (5 if side == "right" else 0)) % W, (3 * i) % H
                img = texture[y : y + H, x : x + W].astype(np.int16)
                img = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
                log.write_image(f"/uav1/stereo/{side}/image_raw", stamp, img, cam.frame_id)
                log.write_camera_info(f"/uav1/stereo/{side}/camera_info", stamp, cam)
    return path


@pytest.fixture(scope="module")
def logs_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("bench")
    write_log(d / "short.mcap", 60)
    write_log(d / "long.mcap", 600, seed=1)
    return d


def _best_of(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def test_decode_throughput(logs_dir: Path) -> None:
    path = logs_dir / "short.mcap"
    cfg = load_config().logs
    topics = ["/uav1/stereo/left/image_raw", "/uav1/stereo/right/image_raw"]

    def cvslam_read() -> int:
        logs = LogSet([McapLogSource(path)], cfg)
        return sum(2 for r in logs.records() if isinstance(r, StereoFrame))

    def bare_read() -> int:
        with path.open("rb") as f:
            return sum(1 for _ in make_reader(f).iter_messages(topics=topics))

    n_images = cvslam_read()
    assert n_images == bare_read() == 120
    t_ours, t_bare = _best_of(cvslam_read), _best_of(bare_read)
    ours, bare = n_images / t_ours, n_images / t_bare
    print(
        f"\n[bench] decode 752x480 mono8: cvslam {ours:8.0f} images/s | bare mcap iteration "
        f"(no decoding) {bare:8.0f} images/s | ratio {ours / bare:.2f} | target >= 500"
    )
    assert ours >= 500


_PEAK = textwrap.dedent("""
    import resource, sys
    from pathlib import Path
    from cvslam_cli.config import load_config
    from cvslam_cli.io.logs import open_logs
    logs = open_logs([Path(sys.argv[1])], load_config().logs)
    n = 0
    if sys.argv[2] == "read":
        n = sum(1 for _ in logs.records())
    print(n, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
""")


def _peak_kib(path: Path, mode: str) -> tuple[int, int]:
    out = subprocess.run(
        [sys.executable, "-c", _PEAK, str(path), mode], check=True, capture_output=True, text=True
    ).stdout.split()
    return int(out[0]), int(out[1])


def test_peak_memory_flat_with_log_length(logs_dir: Path) -> None:
    _, base = _peak_kib(logs_dir / "short.mcap", "open")
    n_short, short = _peak_kib(logs_dir / "short.mcap", "read")
    n_long, long_ = _peak_kib(logs_dir / "long.mcap", "read")
    size_ratio = (logs_dir / "long.mcap").stat().st_size / (logs_dir / "short.mcap").stat().st_size
    print(
        f"\n[bench] peak RSS: open only {base / 1024:.0f} MiB | short log ({n_short} records) "
        f"{short / 1024:.0f} MiB | 10x log ({n_long} records, {size_ratio:.1f}x bytes) "
        f"{long_ / 1024:.0f} MiB | long/short {long_ / short:.2f} | reading adds "
        f"{(short - base) / 1024:.0f} vs {(long_ - base) / 1024:.0f} MiB"
    )
    assert n_long > 9 * n_short
    assert long_ / short < 1.15


STORAGES = {
    "rosbag2 folder (mcap)": ("folder", "mcap", None),
    "sqlite3 .db3": ("db3", "sqlite3", None),
    "ROS 1 .bag": ("bag", None, None),
    "zstd file-compressed .mcap.zstd": ("zstd", "mcap", "file"),
}


def convert_log(src: Path, kind: str) -> Path:
    """`src` (a bare .mcap) in another storage, written by rosbags' converter."""
    from rosbags.convert.converter import convert
    from rosbags.typesys import Stores, get_typestore

    folder, storage, mode = STORAGES[kind]
    dst = src.with_name(f"{src.stem}_{folder}" + (".bag" if folder == "bag" else ""))
    if not dst.exists():
        ros1 = get_typestore(Stores.ROS1_NOETIC) if folder == "bag" else None
        convert(
            [src],
            dst,
            storage or "mcap",
            9,
            "zstd" if mode else None,
            mode or "file",
            None,
            ros1,
            (),
            (),
            (),
            (),
        )
    if folder == "db3":
        return next(dst.glob("*.db3"))
    if folder == "zstd":
        return next(dst.glob("*.mcap.zstd"))
    return dst


@pytest.mark.parametrize("kind", list(STORAGES))
def test_decode_throughput_per_storage(logs_dir: Path, kind: str) -> None:
    cfg = load_config().logs
    bare, other = logs_dir / "short.mcap", convert_log(logs_dir / "short.mcap", kind)

    def read(path: Path) -> int:
        return sum(2 for r in open_logs([path], cfg).records() if isinstance(r, StereoFrame))

    assert read(other) == read(bare) == 120
    t_fast, t_other = _best_of(lambda: read(bare)), _best_of(lambda: read(other))
    print(
        f"\n[bench] decode 752x480 mono8, {kind}: {120 / t_other:8.0f} images/s | .mcap fast "
        f"path {120 / t_fast:8.0f} images/s | ratio {t_fast / t_other:.2f}"
    )


@pytest.mark.parametrize("kind", ["sqlite3 .db3", "ROS 1 .bag", "rosbag2 folder (mcap)"])
def test_peak_memory_flat_with_log_length_per_storage(logs_dir: Path, kind: str) -> None:
    short, long_ = (convert_log(logs_dir / f"{n}.mcap", kind) for n in ("short", "long"))
    n_short, rss_short = _peak_kib(short, "read")
    n_long, rss_long = _peak_kib(long_, "read")
    print(
        f"\n[bench] peak RSS, {kind}: short log ({n_short} records) {rss_short / 1024:.0f} MiB | "
        f"10x log ({n_long} records) {rss_long / 1024:.0f} MiB | long/short "
        f"{rss_long / rss_short:.2f}"
    )
    assert n_long > 9 * n_short
    assert rss_long / rss_short < 1.15


def test_chunk_crc_cost(tmp_path, monkeypatch):
    """What checking every chunk against its CRC (issue 16) costs: `LogSet.records()` with
    the check against the same reader with it switched off, interleaved, same run."""
    import cvslam_cli.io.mcap_scan as scan

    path = write_log(tmp_path / "a.mcap", 120)
    checked = scan.get_chunk_data_stream

    def unchecked(chunk, validate_crc=False):
        return checked(chunk, validate_crc=False)

    def rate():
        t0, n = time.perf_counter(), 0
        for rec in LogSet([McapLogSource(path)], load_config().logs).records():
            n += 2 if isinstance(rec, StereoFrame) else 0
        return n / (time.perf_counter() - t0)

    rates: dict[str, list[float]] = {"crc": [], "off": []}
    for _ in range(3):
        monkeypatch.setattr(scan, "get_chunk_data_stream", checked)
        rates["crc"].append(rate())
        monkeypatch.setattr(scan, "get_chunk_data_stream", unchecked)
        rates["off"].append(rate())
    crc, off = sorted(rates["crc"])[1], sorted(rates["off"])[1]
    print(f"\n[bench] chunk CRC: checked {crc:.0f} images/s | off {off:.0f} images/s | "
          f"ratio {crc / off:.2f}")  # fmt: skip
    assert crc / off > 0.6  # target: the check costs well under half the reading
