"""Every rosbag2 storage, ROS 1 and compressed MCAP read back as the same records: bags written
by `rosbags` (an independent writer) from the real EuRoC clip, each read through `open_logs`,
compared with the bare MCAP file read by the `mcap` fast path."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.errors import LogError
from cvslam_cli.io.log_open import DecompressedMcapSource, open_log
from cvslam_cli.io.logs import open_logs
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.rosbags_source import RosbagsLogSource
from cvslam_cli.records.log import ImuSample, StereoFrame
from tests.io.rosbag_fixtures import (
    euroc_messages,
    only_file,
    write_ros1,
    write_rosbag2,
    write_split_rosbag2,
)

N_PAIRS = 6


@pytest.fixture(scope="module")
def bags(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The same messages in every storage this tool reads."""
    mav0 = shared_data / "euroc_v101_micro" / "mav0"
    if not mav0.is_dir():
        pytest.skip(f"{mav0} not found")
    items = euroc_messages(mav0, N_PAIRS)
    tmp = tmp_path_factory.mktemp("bags")
    mcap_dir = write_rosbag2(items, tmp / "mcap_bag")
    db3_dir = write_rosbag2(items, tmp / "db3_bag", storage="sqlite3")
    zfile_dir = write_rosbag2(items, tmp / "zfile_bag", compression="file")
    return {
        "mcap": only_file(mcap_dir, "*.mcap"),
        "folder_split": write_split_rosbag2(items, tmp / "split_bag", tmp / "parts"),
        "folder_db3": db3_dir,
        "db3": only_file(db3_dir, "*.db3"),
        "ros1": write_ros1(items, tmp / "v101.bag"),
        "folder_zstd_file": zfile_dir,
        "mcap_zstd": only_file(zfile_dir, "*.mcap.zstd"),
        "folder_zstd_message": write_rosbag2(items, tmp / "zmsg_bag", compression="message"),
    }


def _records(path: Path) -> list[tuple[Any, ...]]:
    logs = open_logs([path], load_config().logs)
    out: list[tuple[Any, ...]] = []
    for rec in logs.records():
        if isinstance(rec, StereoFrame):
            out.append(("stereo", rec.vehicle, rec.stamp_ns, rec.left.image, rec.right.image))
        elif isinstance(rec, ImuSample):
            out.append(("imu", rec.vehicle, rec.stamp_ns, rec.gyro_rad_s, rec.accel_m_s2))
        else:
            out.append((type(rec).__name__, rec.stamp_ns))
    return out


def _same(a: list[tuple[Any, ...]], b: list[tuple[Any, ...]]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x[:3] == y[:3]
        for u, v in zip(x[3:], y[3:], strict=True):
            assert u.dtype == v.dtype and np.array_equal(u, v)


@pytest.mark.realdata
@pytest.mark.parametrize(
    "kind",
    [
        "folder_split",
        "folder_db3",
        "db3",
        "ros1",
        "folder_zstd_file",
        "mcap_zstd",
        "folder_zstd_message",
    ],
)
def test_every_storage_gives_the_records_of_the_bare_mcap(bags, kind):
    reference = _records(bags["mcap"])
    frames = [r for r in reference if r[0] == "stereo"]
    assert len(frames) == N_PAIRS and sum(r[0] == "imu" for r in reference) > 5 * N_PAIRS
    _same(_records(bags[kind]), reference)


@pytest.mark.realdata
def test_the_clip_pixels_arrive_unchanged(bags, shared_data):
    import cv2

    mav0 = shared_data / "euroc_v101_micro" / "mav0"
    first = next(r for r in _records(bags["ros1"]) if r[0] == "stereo")
    png = cv2.imread(str(mav0 / "cam1" / "data" / f"{first[2]}.png"), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(first[4], png)


@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["ros1", "folder_db3", "folder_split"])
def test_camera_info_gives_the_same_rig_in_every_storage(bags, kind):
    """ROS 1's CameraInfo (D K R P) is migrated to the ROS 2 names, so its rig is the same."""
    cfg = load_config().logs
    ref = open_logs([bags["mcap"]], cfg).rig("uav1").describe()
    assert open_logs([bags[kind]], cfg).rig("uav1").describe() == ref
    assert ref["left"]["fx"] == pytest.approx(458.654)


@pytest.mark.realdata
def test_the_dispatch_picks_the_reader_by_what_the_path_is(bags):
    assert isinstance(open_log(bags["mcap"]), McapLogSource)
    assert isinstance(open_log(bags["mcap_zstd"]), DecompressedMcapSource)
    for kind in ("folder_split", "db3", "ros1"):
        src = open_log(bags[kind])
        assert isinstance(src, RosbagsLogSource)
        assert src.topics()["/uav1/imu"].message_count > 5 * N_PAIRS
    meta = open_log(bags["folder_split"] / "metadata.yaml")
    assert isinstance(meta, RosbagsLogSource) and meta.path == bags["folder_split"]


def test_what_is_not_a_log_is_refused_naming_the_kinds_accepted(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(LogError, match=r"notes\.txt: not a log .*rosbag2 folder"):
        open_log(text)
    with pytest.raises(LogError, match=r"without metadata\.yaml"):
        open_log(tmp_path)
    with pytest.raises(LogError, match="file not found"):
        open_log(tmp_path / "missing.bag")
    bad = tmp_path / "bad.bag"
    bad.write_bytes(b"#ROSBAG V2.0\nnot really")
    with pytest.raises(LogError, match=r"bad\.bag: cannot read this ros1 bag"):
        open_log(bad)
