"""TUM and KITTI trajectory files: exact round trips and one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.rotations import quat_xyzw_to_matrix
from cvslam_cli.io.textfiles import seconds_text_to_ns
from cvslam_cli.io.trajectory import read_kitti, read_tum, write_kitti, write_tum
from cvslam_cli.records.poses import PoseTable


def random_table(n: int = 50, seed: int = 0, t0_ns: int = 1_403_715_273_262_142_976) -> PoseTable:
    rng = np.random.default_rng(seed)
    stamps = t0_ns + np.cumsum(rng.integers(1, 100_000_000, n)).astype(np.int64)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return PoseTable(stamps, rng.normal(scale=100.0, size=(n, 3)), q)


def test_tum_round_trip_is_exact_in_stamps_and_to_the_written_decimals(tmp_path):
    table = random_table()
    path = tmp_path / "uav1.tum"
    write_tum(path, table, header="estimated\ntrajectory")
    back = read_tum(path)
    assert back.stamps_ns.dtype == np.int64
    np.testing.assert_array_equal(back.stamps_ns, table.stamps_ns)
    np.testing.assert_allclose(back.p_nav_m, table.p_nav_m, rtol=0, atol=5e-10)
    np.testing.assert_allclose(back.q_nav_body_xyzw, table.q_nav_body_xyzw, rtol=0, atol=5e-10)
    # writing what was read gives the same bytes: read_tum is the exact inverse
    again = tmp_path / "again.tum"
    write_tum(again, back, header="estimated\ntrajectory")
    assert again.read_bytes() == path.read_bytes()
    assert not list(tmp_path.glob("*.partial"))


def test_tum_negative_and_small_stamps_and_empty_table(tmp_path):
    table = random_table(5, seed=1, t0_ns=-2_000_000_001)
    write_tum(tmp_path / "a.tum", table)
    np.testing.assert_array_equal(read_tum(tmp_path / "a.tum").stamps_ns, table.stamps_ns)
    empty = PoseTable(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)))
    write_tum(tmp_path / "e.tum", empty)
    back = read_tum(tmp_path / "e.tum")
    assert len(back) == 0 and back.p_nav_m.shape == (0, 3) and back.q_nav_body_xyzw.shape == (0, 4)


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("1403715273.262142976", 1_403_715_273_262_142_976),
        ("1403715273.262142976499", 1_403_715_273_262_142_976),
        ("0.0000000005", 0),  # half to even
        ("0.0000000015", 2),
        ("1.5e-3", 1_500_000),
        ("-0.5", -500_000_000),
        ("9223372035", 9_223_372_035_000_000_000),
    ],
)
def test_seconds_text_is_parsed_exactly(text, ns):
    assert seconds_text_to_ns(text) == ns


def test_tum_reader_skips_comments_and_accepts_commas(tmp_path):
    path = tmp_path / "t.tum"
    path.write_text("# a comment\n\n1.5, 1 2 3 0 0 0 1\n  # indented comment\n2 4 5 6 0 0 1 0\n")
    table = read_tum(path)
    np.testing.assert_array_equal(table.stamps_ns, [1_500_000_000, 2_000_000_000])
    np.testing.assert_array_equal(table.p_nav_m, [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    ("body", "expected"),
    [
        ("1 2 3 4 0 0 0 1\n2 1 2 3 0 0 1\n", "line 3: expected 8 numbers"),
        ("1 2 3 4 0 0 0 1\n2 1 2 x 0 0 0 1\n", "line 3: expected 8 finite numbers"),
        ("1 2 3 4 0 0 0 1\n2 1 2 nan 0 0 0 1\n", "line 3: expected 8 finite numbers"),
        ("1 2 3 4 0 0 0 1\n1 1 2 3 0 0 0 1\n", "line 3: timestamp 1.000000000 s does not"),
        ("1 2 3 4 0 0 0 2\n", "line 2: quaternion norm 2.0000"),
    ],
)
def test_tum_reader_errors_name_file_and_line(tmp_path, body, expected):
    path = tmp_path / "bad.tum"
    path.write_text("# t x y z qx qy qz qw\n" + body)
    with pytest.raises(CvslamError) as err:
        read_tum(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and expected in msg


def test_tum_missing_file_is_one_line(tmp_path):
    with pytest.raises(CvslamError, match=r"nowhere\.tum: not found, expected a TUM trajectory"):
        read_tum(tmp_path / "nowhere.tum")


def test_kitti_round_trip(tmp_path):
    table = random_table(30, seed=2)
    path = tmp_path / "uav1.kitti"
    write_kitti(path, table)
    lines = path.read_text().splitlines()
    assert len(lines) == 30 and all(len(line.split()) == 12 for line in lines)
    T0 = np.array(lines[0].split(), dtype=float).reshape(3, 4)
    np.testing.assert_allclose(T0[:, :3], quat_xyzw_to_matrix(table.q_nav_body_xyzw[0]), atol=1e-15)
    np.testing.assert_array_equal(T0[:, 3], table.p_nav_m[0])
    back = read_kitti(path, table.stamps_ns)
    np.testing.assert_array_equal(back.stamps_ns, table.stamps_ns)
    np.testing.assert_array_equal(back.p_nav_m, table.p_nav_m)  # shortest repr: exact
    # same rotation (q and -q are the same one)
    dots = np.abs(np.sum(back.q_nav_body_xyzw * table.q_nav_body_xyzw, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-12)
    default = read_kitti(path)
    np.testing.assert_array_equal(default.stamps_ns, np.arange(30) * 1_000_000_000)


def test_kitti_reader_reorthonormalises_six_digit_rotations(tmp_path):
    rng = np.random.default_rng(4)
    q = rng.normal(size=4)
    R = quat_xyzw_to_matrix(q / np.linalg.norm(q))
    path = tmp_path / "gt.txt"
    path.write_text(" ".join(f"{v:.6e}" for v in np.hstack([R, [[1], [2], [3]]]).ravel()) + "\n")
    back = read_kitti(path)
    R_back = quat_xyzw_to_matrix(back.q_nav_body_xyzw[0])
    np.testing.assert_allclose(R_back, R, atol=1e-5)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1", "line 2: expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 z", "line 2: expected 12 finite numbers"),
        ("2 0 0 0 0 1 0 0 0 0 1 0", "line 2: the left 3x3 block is not a rotation"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0", "line 2: the left 3x3 block is not a rotation"),
    ],
)
def test_kitti_reader_errors(tmp_path, line, expected):
    path = tmp_path / "bad.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" + line + "\n")
    with pytest.raises(CvslamError) as err:
        read_kitti(path)
    assert str(path) in str(err.value) and expected in str(err.value)


def test_kitti_stamps_must_match_the_poses(tmp_path):
    path = tmp_path / "k.txt"
    write_kitti(path, random_table(3))
    with pytest.raises(CvslamError, match="3 poses"):
        read_kitti(path, np.arange(4, dtype=np.int64))
    with pytest.raises(CvslamError, match=r"k\.txt: line 3: timestamp 0\.000000005 s does not"):
        read_kitti(path, np.array([0, 5, 5], dtype=np.int64))
