"""Output files of `cvslam fuse`: map CSV/PLY, pose covariances, CSV tables, result.mcap."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.fuse_files import (
    MAP_COLUMNS,
    load_pose_covariances,
    read_map_csv,
    save_pose_covariances,
    write_csv_atomic,
    write_map_csv,
    write_map_ply,
)
from cvslam_cli.records.landmarks import LandmarkMap


def random_map(n: int = 40, seed: int = 0) -> LandmarkMap:
    rng = np.random.default_rng(seed)
    first = rng.integers(0, 10**10, n)
    names = ("uav1", "uav2", "ugv1", "uav1;uav2", "uav1;uav2;ugv1")
    return LandmarkMap(
        landmark_id=rng.permutation(10 * n)[:n].astype(np.int64),
        p_nav_m=rng.normal(scale=10.0 ** rng.uniform(-3, 4, (n, 1)), size=(n, 3)),
        std_m=np.abs(rng.normal(scale=0.5, size=(n, 3))),
        observers=tuple(str(names[k]) for k in rng.integers(0, len(names), n)),
        n_observations=rng.integers(1, 500, n),
        first_seen_ns=first,
        last_seen_ns=first + rng.integers(0, 10**9, n),
        in_state=rng.random(n) < 0.5,
        true_id=rng.integers(-2, 10 * n, n),
    )


def assert_same_map(a: LandmarkMap, b: LandmarkMap) -> None:
    for name in (
        "landmark_id",
        "p_nav_m",
        "std_m",
        "n_observations",
        "first_seen_ns",
        "last_seen_ns",
        "in_state",
    ):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.observers == b.observers


# -- map.csv --------------------------------------------------------------------------------


def test_map_csv_round_trip_is_exact(tmp_path):
    table = random_map()
    path = tmp_path / "fuse" / "map.csv"
    write_map_csv(path, table)
    assert path.read_text().splitlines()[0] == ",".join(MAP_COLUMNS)
    assert_same_map(read_map_csv(path), table)
    assert not list(path.parent.glob("*.partial"))
    # pandas reads it too, with the expected dtypes
    frame = pd.read_csv(path)
    assert frame["in_state"].dtype == bool and frame["id"].dtype == np.int64
    np.testing.assert_array_equal(frame["x_m"].to_numpy(), table.p_nav_m[:, 0])


def test_empty_map_round_trips(tmp_path):
    empty = LandmarkMap(
        np.zeros(0, np.int64),
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        (),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, bool),
        np.zeros(0, np.int64),
    )
    write_map_csv(tmp_path / "map.csv", empty)
    back = read_map_csv(tmp_path / "map.csv")
    assert len(back) == 0 and back.p_nav_m.shape == (0, 3)
    write_map_ply(tmp_path / "map.ply", empty)
    header, data = parse_ply(tmp_path / "map.ply")
    assert "element vertex 0" in header and len(data) == 0


def test_map_csv_nan_std_round_trips(tmp_path):
    table = random_map(5, seed=1)
    std = table.std_m.copy()
    std[2, 1] = np.nan
    t2 = LandmarkMap(**{**vars(table), "std_m": std})
    write_map_csv(tmp_path / "m.csv", t2)
    back = read_map_csv(tmp_path / "m.csv")
    assert np.isnan(back.std_m[2, 1]) and np.isnan(back.std_m).sum() == 1


def test_map_csv_true_id_read_when_present_else_unknown(tmp_path):
    table = random_map(6, seed=4)
    path = tmp_path / "map.csv"
    write_map_csv(path, table)
    assert "true_id" not in path.read_text().splitlines()[0]
    np.testing.assert_array_equal(read_map_csv(path).true_id, np.full(6, -1))
    frame = pd.read_csv(path)
    frame["true_id"] = table.true_id
    frame.to_csv(path, index=False)
    back = read_map_csv(path)
    assert back.true_id.dtype == np.int64
    np.testing.assert_array_equal(back.true_id, table.true_id)


def _edit_csv(tmp_path, edit):
    path = tmp_path / "map.csv"
    write_map_csv(path, random_map(4, seed=3))
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")
    return path


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (
            lambda ls: [ls[0].replace(",std_y_m", ",sy"), *ls[1:]],
            "missing column(s) std_y_m",
        ),
        (
            lambda ls: [*ls[:2], ls[2].replace(",", ",x", 1), *ls[3:]],
            "line 3: column x_m: expected a number, got 'x",
        ),
        (
            lambda ls: [*ls[:3], "1.5" + ls[3][ls[3].index(",") :], *ls[4:]],
            "line 4: column id: expected an integer, got '1.5'",
        ),
        (
            lambda ls: [*ls[:4], ",maybe,".join(ls[4].rsplit(",", 2)[::2])],
            "line 5: column in_state: expected True or False, got 'maybe'",
        ),
        (lambda ls: [*ls[:2], ls[2] + ",extra", *ls[3:]], "line 3: 14 fields, the header has 13"),
        (lambda ls: [], "empty file"),
        (
            lambda ls: [ls[0], ls[1], ls[1]],
            "not a usable map (LandmarkMap.landmark_id: id",
        ),
    ],
)
def test_map_csv_errors_are_one_line_naming_the_file(tmp_path, edit, expected):
    path = _edit_csv(tmp_path, edit)
    with pytest.raises(CvslamError) as err:
        read_map_csv(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(path)) and expected in msg, msg


def test_map_csv_missing_file(tmp_path):
    with pytest.raises(CvslamError, match=r"map\.csv: not found, expected a landmark map CSV"):
        read_map_csv(tmp_path / "map.csv")


# -- map.ply --------------------------------------------------------------------------------

_PLY_NUMPY = {"float": "<f4", "int": "<i4", "uint": "<u4", "double": "<f8", "uchar": "u1"}


def parse_ply(path):
    """A minimal independent PLY reader: (header text, structured vertex array)."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii")
    lines = header.splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count, props = None, []
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[0] == "property":
            props.append((words[2], _PLY_NUMPY[words[1]]))
    data = np.frombuffer(raw[end:], dtype=np.dtype(props))
    assert len(data) == count
    return header, data


def test_map_ply_parses_back(tmp_path):
    table = random_map(25, seed=5)
    path = tmp_path / "map.ply"
    write_map_ply(path, table)
    header, v = parse_ply(path)
    assert v.dtype.names == ("x", "y", "z", "id", "std", "n_obs")
    assert "property float x" in header and "property int id" in header
    np.testing.assert_array_equal(v["x"], table.p_nav_m[:, 0].astype(np.float32))
    np.testing.assert_array_equal(v["z"], table.p_nav_m[:, 2].astype(np.float32))
    np.testing.assert_array_equal(v["id"], table.landmark_id)
    np.testing.assert_array_equal(v["std"], table.std_m.max(axis=1).astype(np.float32))
    np.testing.assert_array_equal(v["n_obs"], table.n_observations)
    assert not list(tmp_path.glob("*.partial"))


def test_map_ply_refuses_ids_beyond_int32(tmp_path):
    table = random_map(3, seed=6)
    big = LandmarkMap(**{**vars(table), "landmark_id": np.array([1, 2, 2**40])})
    with pytest.raises(ValueError, match="int32"):
        write_map_ply(tmp_path / "map.ply", big)
    assert not list(tmp_path.iterdir())


# -- pose covariances ------------------------------------------------------------------------


def _covs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 6, 6))
    return np.arange(n, dtype=np.int64) * 50_000_000 + 7, A @ A.transpose(0, 2, 1)


def test_pose_covariances_round_trip_and_reproducible_bytes(tmp_path):
    stamps, cov = _covs(20, seed=7)
    a, b = tmp_path / "a" / "uav1_pose_cov.npz", tmp_path / "b.npz"
    save_pose_covariances(a, stamps, cov)
    save_pose_covariances(b, stamps, cov)
    assert a.read_bytes() == b.read_bytes()
    s2, c2 = load_pose_covariances(a)
    assert s2.dtype == np.int64 and c2.dtype == np.float64
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_array_equal(c2, cov)
    with np.load(a) as npz:
        assert str(npz["format"]) == "cvslam.pose_covariance" and int(npz["version"]) == 1
        assert list(npz["components"]) == [
            "x_m",
            "y_m",
            "z_m",
            "roll_rad",
            "pitch_rad",
            "yaw_rad",
        ]


def test_pose_covariances_refuse_other_versions_and_shapes(tmp_path):
    stamps, cov = _covs(3, seed=8)
    with pytest.raises(ValueError, match=r"cov: expected .* \(F, 6, 6\) = \(3, 6, 6\)"):
        save_pose_covariances(tmp_path / "x.npz", stamps, cov[:, :3, :3])
    path = tmp_path / "v2.npz"
    np.savez(path, format=np.array("cvslam.pose_covariance"), version=np.array(2))
    with pytest.raises(CvslamError) as err:
        load_pose_covariances(path)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and "version 2" in msg
    other = tmp_path / "other.npz"
    np.savez(other, stamps_ns=stamps)
    with pytest.raises(CvslamError, match="not a cvslam pose covariance file"):
        load_pose_covariances(other)
    corrupt = tmp_path / "corrupt.npz"
    np.savez(
        corrupt,
        format=np.array("cvslam.pose_covariance"),
        version=np.array(1),
        stamps_ns=stamps,
        cov=cov[:2],
    )
    with pytest.raises(CvslamError, match="corrupt pose covariance file"):
        load_pose_covariances(corrupt)
    with pytest.raises(CvslamError, match="not found"):
        load_pose_covariances(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(CvslamError, match="not a readable pose covariance file"):
        load_pose_covariances(tmp_path / "junk.npz")


# -- CSV tables -----------------------------------------------------------------------------


def test_write_csv_atomic_floats_read_back_exactly(tmp_path):
    rng = np.random.default_rng(9)
    x = rng.normal(size=500) * 10.0 ** rng.uniform(-300, 300, 500)
    frame = pd.DataFrame(
        {
            "stamp_ns": np.arange(500, dtype=np.int64) * 10**9,
            "vehicle": ["uav1", "ugv2"] * 250,
            "sigma_m": x,
            "nis": np.where(np.arange(500) % 7 == 0, np.nan, x),
        }
    )
    path = tmp_path / "fuse" / "timeline.csv"
    write_csv_atomic(path, frame)
    text = path.read_text()
    assert text.startswith("stamp_ns,vehicle,sigma_m,nis\n") and "\r" not in text
    back = pd.read_csv(path)
    np.testing.assert_array_equal(back["sigma_m"].to_numpy(), x)
    np.testing.assert_array_equal(back["nis"].to_numpy(), frame["nis"].to_numpy())
    np.testing.assert_array_equal(back["stamp_ns"].to_numpy(), frame["stamp_ns"].to_numpy())
    # exact with the standard library too (no pandas-specific parsing needed)
    rows = [line.split(",") for line in text.splitlines()[1:]]
    np.testing.assert_array_equal([float(r[2]) for r in rows], x)
    assert not list(path.parent.glob("*.partial"))
