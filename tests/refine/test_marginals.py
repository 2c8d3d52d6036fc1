"""Marginal covariances from the scaled sparse factorisation (`refine/marginals.py`):
equal to GTSAM's where GTSAM's Cholesky accepts the graph, right where its unscaled pivot
test refuses a determinate one, and a singular graph refused."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cvslam_cli.refine import marginals


def _chain(
    prior_sigma: float, between_sigma: float
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Two points: a prior on the first (sigma `prior_sigma`), the second 1 m from it
    (sigma `between_sigma`)."""
    a, b = gtsam.symbol("l", 0), gtsam.symbol("l", 1)
    g = gtsam.NonlinearFactorGraph()
    g.add(
        gtsam.PriorFactorPoint3(
            a, gtsam.Point3(1, 2, 3), gtsam.noiseModel.Isotropic.Sigma(3, prior_sigma)
        )
    )
    g.add(
        gtsam.BetweenFactorPoint3(
            a, b, gtsam.Point3(0, 0, 1), gtsam.noiseModel.Isotropic.Sigma(3, between_sigma)
        )
    )
    v = gtsam.Values()
    v.insert(a, gtsam.Point3(1, 2, 3))
    v.insert(b, gtsam.Point3(1, 2, 4))
    return g, v


def test_a_graph_gtsams_pivot_test_refuses_is_solved() -> None:
    # 1 m prior, 10 um between: determinate (cov of the second point (1 + 1e-10) I), but
    # the pivots differ by 1e5 and GTSAM's Cholesky calls the system indeterminate
    g, v = _chain(1.0, 1e-5)
    with pytest.raises(RuntimeError, match="Indeterminate"):
        gtsam.Marginals(g, v)
    cov = marginals.factorise(g, v).covariances([gtsam.symbol("l", 0), gtsam.symbol("l", 1)])
    # the normal equations lose digits in proportion to the scaled condition (2e10 here)
    np.testing.assert_allclose(cov[0], np.eye(3), rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(cov[1], (1 + 1e-10) * np.eye(3), rtol=1e-5, atol=1e-12)


def _pose_graph(seed: int) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int], list[int]]:
    """12 poses along x looking along +z (a prior on the first, odometry between them, a
    loop from the last to the first), 20 points 10 m ahead, each projected into 4 poses."""
    rng = np.random.default_rng(seed)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    xs = [gtsam.symbol("x", i) for i in range(12)]
    ls = [gtsam.symbol("l", j) for j in range(20)]
    poses = [
        gtsam.Pose3(
            gtsam.Rot3.RzRyRx(*(0.02 * rng.standard_normal(3))), np.array([0.5 * i, 0.0, 0.0])
        )
        for i in range(12)
    ]
    odometry = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.02, 0.1, 0.1, 0.05]))
    g.add(gtsam.PriorFactorPose3(xs[0], poses[0], gtsam.noiseModel.Isotropic.Sigma(6, 0.05)))
    for i in range(11):
        g.add(gtsam.BetweenFactorPose3(xs[i], xs[i + 1], poses[i].between(poses[i + 1]), odometry))
    g.add(gtsam.BetweenFactorPose3(xs[11], xs[0], poses[11].between(poses[0]), odometry))
    K = gtsam.Cal3_S2(400.0, 400.0, 0.0, 320.0, 240.0)
    pixel = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
    for point in ls:
        p = np.array([rng.uniform(0.0, 5.5), rng.uniform(-2.0, 2.0), rng.uniform(8.0, 12.0)])
        v.insert(point, p)
        for i in rng.choice(12, 4, replace=False):
            z = gtsam.PinholeCameraCal3_S2(poses[i], K).project(p) + 0.5 * rng.standard_normal(2)
            g.add(gtsam.GenericProjectionFactorCal3_S2(z, pixel, xs[i], point, K))
    for x, pose in zip(xs, poses, strict=True):
        v.insert(x, pose)
    return g, v, xs, ls


@pytest.mark.parametrize("seed", [1, 2])
def test_equal_to_gtsam_where_gtsam_accepts_the_graph(seed: int) -> None:
    g, v, xs, ls = _pose_graph(seed)
    reference = gtsam.Marginals(g, v)
    f = marginals.factorise(g, v)
    for keys, d in ((xs, 6), (ls, 3)):
        cov = f.covariances(keys)
        assert cov.shape == (len(keys), d, d)
        for k, c in zip(keys, cov, strict=True):
            np.testing.assert_allclose(c, reference.marginalCovariance(k), rtol=1e-6, atol=1e-12)


def test_batches_give_the_same_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    g, v, xs, _ = _pose_graph(3)
    whole = marginals.factorise(g, v).covariances(xs)
    monkeypatch.setattr(marginals, "BATCH_COLUMNS", 7)  # batches of one pose, tails of one
    done: list[int] = []
    np.testing.assert_array_equal(marginals.factorise(g, v).covariances(xs, done.append), whole)
    assert sum(done) == len(xs) and len(done) == len(xs)


def test_a_direction_nothing_constrains_is_refused() -> None:
    g, v = _chain(1.0, 1.0)
    g.remove(0)  # no prior: the pair can move together
    with pytest.raises(marginals.IndeterminateError):
        marginals.factorise(g, v)


@pytest.mark.parametrize("batch", [256, 7])
def test_landmarks_by_the_schur_complement_equal_their_own_solves(
    batch: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`poses_and_landmarks`: the landmarks' marginals from the poses' columns (H_ll^-1 +
    G Sigma_PP G^T) are the blocks of H^-1 their own solves give, in any batching, and the
    poses' are unchanged."""
    g, v, xs, ls = _pose_graph(4)
    f = marginals.factorise(g, v)
    poses_alone, own = f.covariances(xs), f.covariances(ls)
    monkeypatch.setattr(marginals, "BATCH_COLUMNS", batch)
    poses, lms = f.poses_and_landmarks(xs, ls)
    np.testing.assert_array_equal(poses, poses_alone)
    np.testing.assert_allclose(lms, own, rtol=1e-9, atol=1e-15)
    # the poses' term matters here: H_ll^-1 alone (the point given the poses) is smaller
    given_poses = marginals._LandmarkBlocks(f, ls, f._columns(xs, 6)).A_inv
    ratio = np.trace(own, axis1=1, axis2=2) / np.trace(given_poses, axis1=1, axis2=2)
    assert np.min(ratio) > 1.05


def test_a_landmark_tied_to_another_landmark_is_refused() -> None:
    """The Schur form needs every landmark factor to end on poses: a factor between two
    landmarks is refused, not silently dropped."""
    g, v, xs, ls = _pose_graph(5)
    g.add(
        gtsam.BetweenFactorPoint3(
            ls[0], ls[1], v.atPoint3(ls[1]) - v.atPoint3(ls[0]),
            gtsam.noiseModel.Isotropic.Sigma(3, 0.1),
        )
    )  # fmt: skip
    with pytest.raises(ValueError, match="other than the poses"):
        marginals.factorise(g, v).poses_and_landmarks(xs, ls)
