"""The map file `map.npz` (`io/map_file.py`): exact round trip, byte reproducibility, refusal
of other formats and versions."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.errors import CvslamError
from cvslam_cli.io.map_file import load_map, save_map
from cvslam_cli.io.npz import save_npz
from cvslam_cli.records.landmark_archive import NEVER_NS, LandmarkArchive, merge_archives

FIELDS = (
    "landmark_id", "true_id", "p_nav_m", "cov_nav_m2", "descriptor", "view_dir_sum_nav",
    "first_seen_ns", "last_seen_ns", "n_observations", "in_state", "evicted_ns",
    "reactivations",
)  # fmt: skip


def random_archive(n: int = 30, seed: int = 0, vehicles=("uav1", "uav2", "ugv1")):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 3, 3))
    first = rng.integers(0, 10**11, n)
    last = first[:, None] + rng.integers(0, 10**10, (n, len(vehicles)))
    last[rng.random((n, len(vehicles))) < 0.4] = NEVER_NS
    in_state = rng.random(n) < 0.5
    return LandmarkArchive(
        vehicles=vehicles,
        landmark_id=rng.permutation(5 * n)[:n],
        true_id=rng.integers(-2, 1000, n),
        p_nav_m=rng.normal(scale=10.0 ** rng.uniform(-3, 4, (n, 1)), size=(n, 3)),
        cov_nav_m2=A @ np.swapaxes(A, 1, 2),
        descriptor=rng.integers(0, 256, (n, 128)),
        view_dir_sum_nav=rng.normal(size=(n, 3)),
        first_seen_ns=first,
        last_seen_ns=last,
        n_observations=rng.integers(1, 300, n),
        in_state=in_state,
        evicted_ns=np.where(in_state, NEVER_NS, first + 5),
        reactivations=rng.integers(0, 3, n),
        coordinates="inverse_depth",
    )


def assert_same(a: LandmarkArchive, b: LandmarkArchive) -> None:
    assert a.vehicles == b.vehicles and a.coordinates == b.coordinates
    np.testing.assert_array_equal(a.batch, b.batch)
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def test_round_trip_is_exact_and_byte_reproducible(tmp_path):
    a = random_archive()
    save_map(tmp_path / "map.npz", a)
    assert_same(load_map(tmp_path / "map.npz"), a)
    save_map(tmp_path / "again.npz", load_map(tmp_path / "map.npz"))
    assert (tmp_path / "again.npz").read_bytes() == (tmp_path / "map.npz").read_bytes()
    assert not list(tmp_path.glob("*.partial"))


def test_batch_marks_round_trip_and_an_older_file_is_a_filters(tmp_path):
    """`batch` marks the landmarks a batch solution estimated (a later run trusts their
    marginals more than a filter's); a file written before it existed is all a filter's."""
    import dataclasses

    a = random_archive()
    a = dataclasses.replace(a, batch=np.arange(len(a)) % 3 == 0)
    save_map(tmp_path / "map.npz", a)
    np.testing.assert_array_equal(load_map(tmp_path / "map.npz").batch, a.batch)
    data = dict(np.load(tmp_path / "map.npz"))
    del data["batch"]
    save_npz(tmp_path / "older.npz", data)
    assert not load_map(tmp_path / "older.npz").batch.any()
    data["batch"] = np.zeros(3, dtype=bool)  # not one per landmark
    save_npz(tmp_path / "other.npz", data)
    with pytest.raises(CvslamError, match=r"other\.npz.*corrupt.*batch"):
        load_map(tmp_path / "other.npz")


def test_empty_map_round_trips(tmp_path):
    a = random_archive(0)
    save_map(tmp_path / "map.npz", a)
    b = load_map(tmp_path / "map.npz")
    assert len(b) == 0 and b.cov_nav_m2.shape == (0, 3, 3) and b.last_seen_ns.shape == (0, 3)


def test_summary_map_and_merge():
    a, b = random_archive(5, 1, ("uav1",)), random_archive(4, 2, ("uav2", "uav1"))
    m = merge_archives([a, b])
    assert m.vehicles == ("uav1", "uav2") and list(m.landmark_id) == list(range(9))
    np.testing.assert_array_equal(m.last_seen_ns[5:, 0], b.last_seen_ns[:, 1])
    np.testing.assert_array_equal(m.last_seen_ns[:5, 1], NEVER_NS)
    lm = m.landmark_map()
    np.testing.assert_allclose(lm.std_m**2, np.diagonal(m.cov_nav_m2, axis1=1, axis2=2))
    assert lm.observers[:5] == tuple("uav1" if s != NEVER_NS else "" for s in a.last_seen_ns[:, 0])


def test_other_formats_versions_and_damage_are_refused(tmp_path):
    save_map(tmp_path / "map.npz", random_archive(3))
    raw = dict(np.load(tmp_path / "map.npz"))
    save_npz(tmp_path / "v2.npz", {**raw, "version": np.array(2)})
    version = r"v2\.npz: map format version 2, this cvslam reads version 1"
    with pytest.raises(CvslamError, match=version):
        load_map(tmp_path / "v2.npz")
    save_npz(tmp_path / "other.npz", {**raw, "format": np.array("cvslam.features")})
    with pytest.raises(CvslamError, match=r"other\.npz: not a cvslam map file"):
        load_map(tmp_path / "other.npz")
    save_npz(tmp_path / "bad.npz", {**raw, "cov_nav_m2": raw["cov_nav_m2"][:2]})
    with pytest.raises(CvslamError, match=r"bad\.npz: corrupt map file .*cov_nav_m2"):
        load_map(tmp_path / "bad.npz")
    with pytest.raises(CvslamError, match=r"missing\.npz: map file not found"):
        load_map(tmp_path / "missing.npz")
