"""Trajectory metrics: closed-form answers on synthetic trajectories, and agreement with evo
(computed here through evo's API; evo is a dev dependency, never imported by cvslam_cli)."""

from __future__ import annotations

import copy
import math
import os

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np
import pytest
from evo.core import filters, metrics, sync, trajectory
from evo.core.metrics import PoseRelation, Unit
from evo.tools import file_interface
from scipy.stats import chi2

from cvslam_cli.evaluation.metrics import (
    ErrorStatistics,
    NoPairsError,
    accumulated_distances_m,
    associate,
    ate,
    final_drift,
    nees_chi2_band,
    nees_position,
    pairs_by_index,
    pairs_by_path,
    path_length_m,
    rpe,
    rpe_per_distance,
)
from cvslam_cli.geometry.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from cvslam_cli.io.trajectory import read_kitti, read_tum, write_tum
from cvslam_cli.records.poses import PoseTable

STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")
S = 1_000_000_000  # ns per second


def rz(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rx(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def table(p: np.ndarray, R: np.ndarray | None = None, stamps_ns=None) -> PoseTable:
    p = np.asarray(p, dtype=float)
    R = np.broadcast_to(np.eye(3), (len(p), 3, 3)) if R is None else R
    stamps = np.arange(len(p), dtype=np.int64) * (S // 10) if stamps_ns is None else stamps_ns
    return PoseTable(np.asarray(stamps, dtype=np.int64), p, matrix_to_quat_xyzw(np.asarray(R)))


def straight(n: int = 101, step_m: float = 1.0) -> PoseTable:
    """Along x at step_m per pose, identity attitude."""
    return table(np.stack([np.arange(n) * step_m, np.zeros(n), np.zeros(n)], axis=1))


def curvy(n: int = 200, seed: int = 0) -> PoseTable:
    """A smooth 3D path with varying heading, attitude along the path."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 4.0 * math.pi, n)
    p = np.stack([20 * np.cos(t / 2), 10 * np.sin(t), 0.5 * t + 0.01 * rng.normal(size=n)], 1)
    R = np.stack([rz(a) @ rx(0.1 * math.sin(3 * a)) for a in t / 2 + math.pi / 2])
    return table(p, R)


def stats(result) -> dict[str, float]:
    return {k: float(getattr(result, k)) for k in STATS}


def rel_diff(ours: dict[str, float], theirs: dict[str, float]) -> dict[str, float]:
    return {k: abs(ours[k] - theirs[k]) / max(abs(theirs[k]), 1e-300) for k in STATS}


def assert_stats_close(ours, theirs: dict[str, float], rtol: float = 1e-6) -> None:
    diff = rel_diff(stats(ours), {k: float(theirs[k]) for k in STATS})
    assert max(diff.values()) <= rtol, diff


# -- statistics, helpers --------------------------------------------------------------------


def test_statistics_follow_evo_definitions():
    e = np.array([1.0, 2.0, 2.0, 5.0])
    s = ErrorStatistics.of(e)
    assert s.rmse == pytest.approx(math.sqrt((1 + 4 + 4 + 25) / 4))
    assert (s.mean, s.median, s.min, s.max, s.sse) == (2.5, 2.0, 1.0, 5.0, 34.0)
    assert s.std == pytest.approx(math.sqrt((1.5**2 + 0.5**2 + 0.5**2 + 2.5**2) / 4))  # ddof 0
    assert s.std == pytest.approx(float(np.std(e)))
    with pytest.raises(ValueError):
        ErrorStatistics.of(np.zeros(0))


def test_path_length_and_accumulated_distances():
    p = np.array([[0.0, 0, 0], [3, 4, 0], [3, 4, 0], [3, 4, 2]])
    assert path_length_m(p) == 7.0
    np.testing.assert_array_equal(accumulated_distances_m(p), [0.0, 5.0, 5.0, 7.0])
    assert path_length_m(p[:1]) == 0.0


# -- association ----------------------------------------------------------------------------


def test_association_with_jittered_stamps_and_missing_poses():
    rng = np.random.default_rng(1)
    n = 300
    ref = straight(n)
    keep = np.sort(rng.choice(n, size=250, replace=False))
    jitter = rng.integers(-3_000_000, 3_000_001, size=len(keep))
    est_stamps = ref.stamps_ns[keep] + jitter
    est = table(ref.p_nav_m[keep], stamps_ns=est_stamps)
    ref_idx, est_idx = associate(ref, est)
    # est (250 poses) is the shorter table: every est pose finds its own ref pose
    np.testing.assert_array_equal(est_idx, np.arange(len(keep)))
    np.testing.assert_array_equal(ref_idx, keep)
    # evo's own matching on float seconds agrees
    m_short, m_long = sync.matching_time_indices(est_stamps / 1e9, ref.stamps_ns / 1e9, 0.01)
    np.testing.assert_array_equal(m_short, est_idx)
    np.testing.assert_array_equal(m_long, ref_idx)
    # a jitter beyond max_diff drops that pose
    far = est_stamps.copy()
    far[10] += 20_000_000
    _, est_idx2 = associate(ref, table(ref.p_nav_m[keep], stamps_ns=far))
    assert 10 not in est_idx2 and len(est_idx2) == len(keep) - 1


def test_association_ties_limits_and_which_table_is_walked():
    ref = table(np.zeros((3, 3)), stamps_ns=np.array([0, 20, 40]) * 1_000_000)
    # halfway (10 ms) between 0 and 20 ms: the lower stamp wins; exactly max_diff accepted
    est = table(np.zeros((3, 3)), stamps_ns=np.array([10, 41, 51]) * 1_000_000)
    ref_idx, est_idx = associate(ref, est)
    np.testing.assert_array_equal(est_idx, [0, 1])
    np.testing.assert_array_equal(ref_idx, [0, 2])
    r2, e2 = associate(ref, est, max_diff_ns=11_000_000)
    np.testing.assert_array_equal(e2, [0, 1, 2])
    np.testing.assert_array_equal(r2, [0, 2, 2])  # the longer table's pose used twice
    # the estimate is longer: the reference is walked, each ref pose takes its nearest est
    dense = table(np.zeros((9, 3)), stamps_ns=np.arange(9) * 5_000_000)
    r3, e3 = associate(ref, dense)
    np.testing.assert_array_equal(r3, [0, 1, 2])
    np.testing.assert_array_equal(e3, [0, 4, 8])
    with pytest.raises(ValueError, match="no matching timestamps"):
        associate(ref, table(np.zeros((2, 3)), stamps_ns=np.array([S, 2 * S])))


def test_association_matches_evo_on_random_stamps():
    rng = np.random.default_rng(7)
    for trial in range(5):
        a = np.cumsum(rng.integers(1_000_000, 30_000_000, size=200)).astype(np.int64)
        b = np.cumsum(rng.integers(1_000_000, 30_000_000, size=150 + 50 * (trial % 2) + trial))
        ref, est = table(np.zeros((len(a), 3)), stamps_ns=a), table(np.zeros((len(b), 3)), None, b)
        ref_idx, est_idx = associate(ref, est)
        evo_ref = trajectory.PoseTrajectory3D(
            np.arange(len(a))[:, None] * np.ones(3), np.tile([1.0, 0, 0, 0], (len(a), 1)), a / 1e9
        )
        evo_est = trajectory.PoseTrajectory3D(
            np.arange(len(b))[:, None] * np.ones(3), np.tile([1.0, 0, 0, 0], (len(b), 1)), b / 1e9
        )
        r, e = sync.associate_trajectories(evo_ref, evo_est, max_diff=0.01)
        np.testing.assert_array_equal(r.positions_xyz[:, 0], ref_idx)
        np.testing.assert_array_equal(e.positions_xyz[:, 0], est_idx)


# -- ATE ------------------------------------------------------------------------------------


def test_ate_pure_translation_offset():
    ref = curvy()
    offset = np.array([0.3, -0.4, 1.2])
    est = PoseTable(ref.stamps_ns, ref.p_nav_m + offset, ref.q_nav_body_xyzw)
    res = ate(ref, est)
    norm = float(np.linalg.norm(offset))
    np.testing.assert_allclose(res.errors_m, norm, rtol=1e-12)
    assert res.rmse == pytest.approx(norm) and res.max == pytest.approx(norm)
    assert res.std == pytest.approx(0.0, abs=1e-12)
    assert res.sse == pytest.approx(len(ref) * norm**2)
    np.testing.assert_array_equal(res.stamps_ns, est.stamps_ns)
    for kind in ("se3", "sim3"):
        aligned = ate(ref, est, kind)
        assert aligned.max < 1e-9
        np.testing.assert_allclose(aligned.alignment.t, -offset, atol=1e-9)
    # the relative error ignores a constant offset
    assert rpe(ref, est, 1).max < 1e-12


def test_ate_rpe_and_final_drift_of_a_constant_drift():
    n = 101
    ref = straight(n)  # 1 m per pose along x
    k = np.arange(n)
    est = PoseTable(
        ref.stamps_ns, ref.p_nav_m + np.outer(k * 0.01, [0.0, 1.0, 0.0]), ref.q_nav_body_xyzw
    )
    res = ate(ref, est)
    np.testing.assert_allclose(res.errors_m, 0.01 * k, atol=1e-12)
    assert res.rmse == pytest.approx(0.01 * math.sqrt(np.mean(k**2.0)))
    assert res.mean == pytest.approx(0.5) and res.median == pytest.approx(0.5)
    # every relative step drifts 1 cm sideways per metre: 1 %
    one = rpe(ref, est, 1)
    np.testing.assert_allclose(one.errors_m, 0.01, rtol=1e-9)
    assert len(one.pairs) == n - 1
    ten = rpe(ref, est, 10, "m", pairs_from_reference=True)
    np.testing.assert_array_equal(ten.pairs[:3], [[0, 10], [10, 20], [20, 30]])
    np.testing.assert_allclose(ten.errors_m, 0.1, rtol=1e-9)
    drift = rpe_per_distance(ref, est, (10.0, 50.0))
    # all pairs within +-10 % of delta: near the end, pairs of 9 m (45 m) still count
    assert [r.n_pairs for r in drift.rows] == [n - 9, n - 45]
    for row in drift.rows:
        np.testing.assert_allclose(row.drift_pct, 1.0, rtol=1e-9)
    assert drift.average_pct == pytest.approx(1.0)
    by_fraction = rpe_per_distance(ref, est, fractions=(0.1,))
    assert by_fraction.rows[0].delta_m == pytest.approx(10.0)
    assert by_fraction.rows[0].mean_pct == pytest.approx(1.0)
    metres, percent = final_drift(ref, est)
    assert metres == pytest.approx(1.0) and percent == pytest.approx(1.0)


def test_rotation_only_error():
    """Same positions, every estimated attitude yawed by theta in the body frame: no ATE; the
    relative translation t = (1, 0, 0) is seen rotated, |Rz(theta)^T t - t| = 2 sin(theta/2)."""
    theta = 0.05
    ref = straight(51)
    R_est = np.broadcast_to(rz(theta), (51, 3, 3))
    est = PoseTable(ref.stamps_ns, ref.p_nav_m.copy(), matrix_to_quat_xyzw(np.asarray(R_est)))
    assert ate(ref, est).max == 0.0
    res = rpe(ref, est, 1, all_pairs=True)
    np.testing.assert_allclose(res.errors_m, 2 * math.sin(theta / 2), rtol=1e-9)
    res5 = rpe(ref, est, 5)
    np.testing.assert_allclose(res5.errors_m, 5 * 2 * math.sin(theta / 2), rtol=1e-9)


def test_sim3_recovers_scale_rotation_and_translation():
    ref = curvy()
    s_true, R_true, t_true = (
        2.5,
        rz(0.7) @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0.0]]),
        [3, 1, 2],
    )
    # est = the reference seen through the inverse similarity: ref = s R est + t
    est_p = (ref.p_nav_m - t_true) @ R_true / s_true
    est_R = R_true.T @ quat_xyzw_to_matrix(ref.q_nav_body_xyzw)
    est = PoseTable(ref.stamps_ns, est_p, matrix_to_quat_xyzw(est_R))
    sim3 = ate(ref, est, "sim3")
    assert sim3.max < 1e-9
    assert sim3.alignment.scale == pytest.approx(s_true)
    np.testing.assert_allclose(sim3.alignment.R, R_true, atol=1e-12)
    np.testing.assert_allclose(sim3.alignment.t, t_true, atol=1e-9)
    assert ate(ref, est, "se3").rmse > 1.0  # rigid alignment cannot undo the scale
    assert rpe(ref, est, 1, align="sim3").max < 1e-9
    assert rpe(ref, est, 1).rmse > 0.1


def test_rpe_input_errors():
    ref = straight(10)
    with pytest.raises(ValueError, match="no pose pair"):
        rpe(ref, ref, 100, "m")
    with pytest.raises(ValueError, match="integer"):
        rpe(ref, ref, 1.5, "frames")
    with pytest.raises(ValueError):
        rpe(ref, ref, -1, "m")
    with pytest.raises(ValueError):
        ate(ref, ref, "affine")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="degenerate"):
        ate(ref, ref, "se3")  # a straight line: the rotation about it is undetermined (evo too)
    with pytest.raises(NoPairsError):
        rpe(ref, ref, 20, "frames")
    empty = rpe_per_distance(ref, ref, (5.0, 100.0))
    assert [r.n_pairs for r in empty.rows] == [5, 0] and math.isnan(empty.rows[1].mean_pct)


# -- pair selection = evo's filters ---------------------------------------------------------


def test_pairs_match_evo_filters_including_stationary_stretches():
    rng = np.random.default_rng(3)
    steps = rng.uniform(0.0, 2.0, size=(400, 3))
    steps[rng.random(400) < 0.3] = 0.0  # standing still: plateaus of equal path distance
    steps[50:60] = [1.0, 0.0, 0.0]  # exact metre steps: pairs landing exactly on delta
    p = np.cumsum(np.vstack([np.zeros((1, 3)), steps]), axis=0)
    poses = [np.block([[np.eye(3), q[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]) for q in p]
    for delta in (0.0, 0.5, 1.0, 3.0, 10.0, 57.3, 2000.0):
        for all_pairs in (False, True):
            theirs = filters.filter_pairs_by_path(poses, delta, 0.1 * delta, all_pairs)
            ours = pairs_by_path(p, delta, 0.1 * delta, all_pairs)
            assert ours.tolist() == [list(x) for x in theirs], (delta, all_pairs)
    for delta in (1, 2, 7, 400, 401):
        for all_pairs in (False, True):
            theirs = filters.filter_pairs_by_index(poses, delta, all_pairs)
            assert pairs_by_index(len(p), delta, all_pairs).tolist() == [list(x) for x in theirs]


def test_rpe_matches_evo_on_synthetic_noisy_trajectory():
    ref = curvy(300, seed=5)
    rng = np.random.default_rng(6)
    R_noise = np.stack([rz(a) for a in np.cumsum(rng.normal(0, 0.002, len(ref)))])
    est_R = quat_xyzw_to_matrix(ref.q_nav_body_xyzw) @ R_noise
    est_p = 1.1 * ref.p_nav_m + np.cumsum(rng.normal(0, 0.05, (len(ref), 3)), axis=0)
    est = PoseTable(ref.stamps_ns, est_p, matrix_to_quat_xyzw(est_R))
    evo_ref, evo_est = evo_path(ref), evo_path(est)
    for kind in ("none", "se3", "sim3"):
        assert_stats_close(ate(ref, est, kind), evo_ape(evo_ref, evo_est, kind), 1e-9)
        for delta, unit, all_pairs in ((1, "frames", False), (3, "frames", True), (5.0, "m", True)):
            ours = rpe(ref, est, delta, unit, all_pairs, kind)
            theirs = evo_rpe(evo_ref, evo_est, delta, unit, all_pairs, kind)
            assert ours.pairs[:, 1].tolist() == theirs.delta_ids
            assert_stats_close(ours, theirs.get_all_statistics(), 1e-9)


# -- NEES -----------------------------------------------------------------------------------


def test_nees_position_closed_form_and_band():
    ref = np.zeros((3, 3))
    est = np.array([[1.0, 0, 0], [0, 2.0, 0], [1.0, 1.0, 1.0]])
    cov = np.stack([np.eye(3), np.diag([1.0, 4.0, 1.0]), 2 * np.eye(3)])
    np.testing.assert_allclose(nees_position(ref, est, cov), [1.0, 1.0, 1.5])
    lo, hi = nees_chi2_band(3, 1)
    assert (lo, hi) == (pytest.approx(chi2.ppf(0.025, 3)), pytest.approx(chi2.ppf(0.975, 3)))
    lo50, hi50 = nees_chi2_band(3, 50)
    assert lo50 == pytest.approx(chi2.ppf(0.025, 150) / 50)
    assert lo < lo50 < 3.0 < hi50 < hi
    # a consistent estimator: samples drawn from the covariance fall in the band ~95 % of runs
    rng = np.random.default_rng(0)
    L = np.linalg.cholesky(np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]]))
    e = rng.normal(size=(4000, 3)) @ L.T
    eps = nees_position(np.zeros_like(e), e, np.broadcast_to(L @ L.T, (4000, 3, 3)))
    assert np.mean(eps) == pytest.approx(3.0, abs=0.15)
    assert np.mean((eps >= lo) & (eps <= hi)) == pytest.approx(0.95, abs=0.015)
    with pytest.raises(ValueError):
        nees_position(ref, est, cov[:2])
    # the horizontal position of a ground robot: 2 dof, mean 2 when consistent
    e2 = rng.normal(size=(4000, 2)) * [1.5, 0.5]
    eps2 = nees_position(
        np.zeros_like(e2), e2, np.broadcast_to(np.diag([2.25, 0.25]), (4000, 2, 2))
    )
    assert np.mean(eps2) == pytest.approx(2.0, abs=0.12)
    with pytest.raises(ValueError):
        nees_position(ref[:, :2], est[:, :2], cov)


# -- evo on the real files ------------------------------------------------------------------


def evo_path(t: PoseTable) -> trajectory.PosePath3D:
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = quat_xyzw_to_matrix(t.q_nav_body_xyzw)
    T[:, :3, 3] = t.p_nav_m
    return trajectory.PosePath3D(poses_se3=list(T))


def evo_ape(evo_ref, evo_est, kind: str) -> dict[str, float]:
    est = copy.deepcopy(evo_est)
    if kind != "none":
        est.align(evo_ref, correct_scale=kind == "sim3")
    metric = metrics.APE(PoseRelation.translation_part)
    metric.process_data((evo_ref, est))
    return metric.get_all_statistics()


def evo_rpe(evo_ref, evo_est, delta, unit: str, all_pairs: bool, kind: str) -> metrics.RPE:
    est = copy.deepcopy(evo_est)
    if kind != "none":
        est.align(evo_ref, correct_scale=kind == "sim3")
    evo_unit = Unit.meters if unit == "m" else Unit.frames
    metric = metrics.RPE(PoseRelation.translation_part, delta, evo_unit, 0.1, all_pairs)
    metric.process_data((evo_ref, est))
    return metric


RPE_CASES = [(1, "frames", False), (100.0, "m", False), (100.0, "m", True)]


@pytest.fixture(scope="module")
def kitti(shared_data):
    folder = shared_data / "reference_trajectories"
    gt, orb = folder / "KITTI_00_gt.txt", folder / "KITTI_00_ORB.txt"
    if not (gt.is_file() and orb.is_file()):
        pytest.skip(f"{folder} lacks KITTI_00_gt.txt / KITTI_00_ORB.txt")
    return {
        "ref": read_kitti(gt),
        "est": read_kitti(orb),
        "evo_ref": file_interface.read_kitti_poses_file(gt),
        "evo_est": file_interface.read_kitti_poses_file(orb),
    }


@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["none", "se3", "sim3"])
def test_kitti_ate_equals_evo_on_the_files(kitti, kind):
    """ATE reads only positions: identical to evo on the files as evo reads them."""
    ours = ate(kitti["ref"], kitti["est"], kind)
    assert len(ours.errors_m) == len(kitti["ref"]) == kitti["evo_ref"].num_poses
    assert_stats_close(ours, evo_ape(kitti["evo_ref"], kitti["evo_est"], kind), 1e-6)


@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["none", "se3", "sim3"])
@pytest.mark.parametrize(("delta", "unit", "all_pairs"), RPE_CASES)
def test_kitti_rpe_equals_evo(kitti, kind, delta, unit, all_pairs):
    """RPE on the same poses: evo given the poses read_kitti produced (1e-6 relative), and evo
    reading the files itself. The KITTI files store 3x3 blocks up to 2.3e-7 away from a
    rotation; evo uses them raw, read_kitti re-orthonormalises: same pairs, per-pair errors
    within 1e-7 m + 3e-7 x the pair's span, statistics within 1e-4 relative (the smallest
    error, ~1 mm, is the most sensitive; the others agree to a few 1e-6)."""
    ours = rpe(kitti["ref"], kitti["est"], delta, unit, all_pairs, kind)
    same = evo_rpe(evo_path(kitti["ref"]), evo_path(kitti["est"]), delta, unit, all_pairs, kind)
    assert ours.pairs[:, 1].tolist() == same.delta_ids
    assert_stats_close(ours, same.get_all_statistics(), 1e-6)
    raw = evo_rpe(kitti["evo_ref"], kitti["evo_est"], delta, unit, all_pairs, kind)
    assert ours.pairs[:, 1].tolist() == raw.delta_ids
    i, j = ours.pairs.T
    span_m = np.linalg.norm(kitti["ref"].p_nav_m[j] - kitti["ref"].p_nav_m[i], axis=1)
    assert np.all(np.abs(ours.errors_m - raw.error) <= 1e-7 + 3e-7 * span_m)
    assert_stats_close(ours, raw.get_all_statistics(), 1e-4)
    # the headline statistics agree to the 1e-6 even from the raw files
    theirs = raw.get_all_statistics()
    for key in ("rmse", "mean"):
        assert getattr(ours, key) == pytest.approx(theirs[key], rel=1e-6), key


@pytest.mark.realdata
def test_tum_files_written_by_us_read_by_evo(kitti, tmp_path):
    """KITTI poses as TUM files with real-looking stamps (10 Hz, the estimate jittered by up to
    3 ms and missing every 7th pose): evo reads our files, associates, and agrees."""
    n = len(kitti["ref"])
    t0 = 1_317_384_500_123_456_789
    ref_stamps = t0 + np.arange(n, dtype=np.int64) * 103_000_000
    keep = np.flatnonzero(np.arange(n) % 7 != 3)
    jitter = np.random.default_rng(2).integers(-3_000_000, 3_000_001, size=len(keep))
    ref0, est0 = kitti["ref"], kitti["est"]
    write_tum(tmp_path / "ref.tum", PoseTable(ref_stamps, ref0.p_nav_m, ref0.q_nav_body_xyzw))
    write_tum(
        tmp_path / "est.tum",
        PoseTable(ref_stamps[keep] + jitter, est0.p_nav_m[keep], est0.q_nav_body_xyzw[keep]),
        header="ORB-SLAM2 on KITTI 00",
    )
    ref, est = read_tum(tmp_path / "ref.tum"), read_tum(tmp_path / "est.tum")
    evo_ref = file_interface.read_tum_trajectory_file(tmp_path / "ref.tum")
    evo_est = file_interface.read_tum_trajectory_file(tmp_path / "est.tum")
    evo_ref, evo_est = sync.associate_trajectories(evo_ref, evo_est, max_diff=0.01)
    ref_idx, est_idx = associate(ref, est)
    np.testing.assert_array_equal(est_idx, np.arange(len(keep)))
    np.testing.assert_array_equal(ref.p_nav_m[ref_idx], evo_ref.positions_xyz)
    np.testing.assert_array_equal(est.p_nav_m[est_idx], evo_est.positions_xyz)
    for kind in ("none", "se3", "sim3"):
        res = ate(ref, est, kind)
        assert_stats_close(res, evo_ape(evo_ref, evo_est, kind), 1e-6)
        np.testing.assert_array_equal(res.stamps_ns, est.stamps_ns)
        for delta, unit, all_pairs in RPE_CASES:
            ours = rpe(ref, est, delta, unit, all_pairs, kind)
            theirs = evo_rpe(evo_ref, evo_est, delta, unit, all_pairs, kind)
            assert ours.pairs[:, 1].tolist() == theirs.delta_ids
            assert_stats_close(ours, theirs.get_all_statistics(), 1e-6)


@pytest.mark.realdata
def test_kitti_drift_figures(kitti):
    """ORB-SLAM2 stereo on KITTI 00 over 100, 200, ..., 800 m: 0.705 % average translational
    drift, the published figure (Mur-Artal & Tardos 2017, table: t_rel 0.70 %); rigid
    alignment does not change it."""
    ref, est = kitti["ref"], kitti["est"]
    assert path_length_m(ref.p_nav_m) == pytest.approx(3724.2, abs=1.0)
    lengths = tuple(100.0 * k for k in range(1, 9))
    summary = rpe_per_distance(ref, est, lengths)
    assert [row.n_pairs for row in summary.rows][::7] == [4458, 3825]
    assert summary.average_pct == pytest.approx(0.705, abs=0.001)
    assert summary.rows[0].mean_pct == pytest.approx(1.011, abs=0.001)
    aligned = rpe_per_distance(ref, est, lengths, align="se3")
    assert aligned.average_pct == pytest.approx(summary.average_pct, rel=1e-9)
    metres, percent = final_drift(ref, est)
    assert percent == pytest.approx(100 * metres / path_length_m(ref.p_nav_m))
