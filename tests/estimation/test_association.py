"""Data association: gating, the descriptor test, one landmark per match, spreading over
the image; the feature types 1/2/3 (`classify`)."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.association import (
    TYPE_1,
    TYPE_2,
    TYPE_3,
    LandmarkErrors,
    LandmarkPrediction,
    _in_boxes,
    associate,
    classify,
    descriptor_tests,
    lookalike_bound,
    lookalike_gates,
    noise_scale,
    pose_consistent,
    spread_order,
    unassociated,
)
from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.settings import SlamSettings

RNG = np.random.default_rng(11)


def _prediction(z: np.ndarray, sigma: float = 1.0) -> LandmarkPrediction:
    k = len(z)
    S = np.broadcast_to(np.eye(4) * sigma**2, (k, 4, 4)).copy()
    return LandmarkPrediction(np.arange(k), z, np.zeros((k, 4, 1)), np.zeros((k, 4, 3)), S)


def test_association_gates_then_takes_the_closest_distinctive_descriptor():
    z = np.array([[100, 100, 90, 100], [300, 200, 280, 200], [500, 300, 490, 300.0]])
    desc_lm = RNG.integers(0, 255, size=(3, 128)).astype(np.uint8)
    # matches: landmark 0 seen (noisy desc) + a look-alike far outside its window;
    # landmark 1 seen twice inside its window with two similar descriptors (ambiguous);
    # landmark 2 not seen; one unrelated match
    z_obs = np.array(
        [
            [100.5, 99.5, 90.2, 99.6],
            [600, 100, 590, 100.0],
            [300.5, 200.2, 280.3, 200.0],
            [299.6, 200.4, 279.8, 200.2],
            [50, 400, 40, 400.0],
        ]
    )
    noise = lambda: RNG.integers(-3, 4, size=128)  # noqa: E731
    d = np.clip(
        np.stack(
            [
                desc_lm[0] + noise(),
                desc_lm[0] + noise(),
                desc_lm[1] + noise(),
                desc_lm[1] + noise(),
                RNG.integers(0, 255, 128),
            ]
        ),
        0,
        255,
    ).astype(np.uint8)
    a = associate(_prediction(z), desc_lm, z_obs, d, gate_chi2=18.47, ratio=0.8, max_distance=350)
    assert list(a.pred_index) == [0] and list(a.match_index) == [0]
    assert list(a.near_landmark) == [True, False, True, True, False]


def test_every_pair_inside_a_window_lies_in_its_bounding_box():
    """The bounding boxes that spare the full gate computation are a necessary condition of
    it: over random correlated innovation covariances, every (landmark, match) pair whose
    chi-square distance passes the gate is inside the landmark's box, and the boxes leave
    most far pairs out (what they are for)."""
    k, M, gate = 200, 300, 18.47
    A = RNG.normal(size=(k, 4, 4)) * RNG.uniform(0.3, 6.0, size=(k, 1, 1))
    S = A @ np.swapaxes(A, 1, 2) + 0.05 * np.eye(4)
    z = RNG.uniform(0, 600, size=(k, 4))
    pred = LandmarkPrediction(np.arange(k), z, np.zeros((k, 4, 1)), np.zeros((k, 4, 3)), S)
    # half the matches drawn from some landmark's innovation distribution (mostly inside its
    # window, some just outside), half anywhere
    j = RNG.integers(0, k, M // 2)
    near = z[j] + 1.5 * np.einsum(
        "mij,mj->mi", np.linalg.cholesky(S[j]), RNG.normal(size=(M // 2, 4))
    )
    z_obs = np.concatenate([near, RNG.uniform(0, 600, size=(M - M // 2, 4))])
    diff = z_obs[None, :, :] - z[:, None, :]
    d2 = np.einsum("kmi,kij,kmj->km", diff, np.linalg.inv(S), diff)
    box = _in_boxes(pred, z_obs, gate)
    assert (d2 < gate).sum() > 100  # the test has pairs inside windows
    assert not np.any((d2 < gate) & ~box)
    assert box.mean() < 0.2


def test_a_match_goes_to_one_landmark_only():
    z = np.array([[100, 100, 90, 100], [101, 100, 91, 100.0]])
    desc_lm = RNG.integers(0, 255, size=(2, 128)).astype(np.uint8)
    d = np.clip(desc_lm[1].astype(int) + 2, 0, 255).astype(np.uint8)[None]
    a = associate(_prediction(z, 2.0), desc_lm, np.array([[100.5, 100, 90.5, 100]]), d,
                  gate_chi2=18.47, ratio=0.8, max_distance=1e9)  # fmt: skip
    assert list(a.pred_index) == [1] and list(a.match_index) == [0]


def test_the_ratio_test_per_landmark():
    """Two landmarks, each with two candidates in its window whose descriptor distances are
    in a ratio of 0.75: accepted at a ratio of 0.8, refused at 0.7, and with one ratio per
    landmark (the stricter for another vehicle's landmark) each by its own."""
    z = np.array([[100, 100, 90, 100], [300, 200, 280, 200.0]])
    desc_lm = np.zeros((2, 128), dtype=np.uint8)
    desc_lm[1, :] = 200
    z_obs = np.array(
        [[100.3, 100, 90.3, 100], [99.7, 100, 89.7, 100], [300.3, 200, 280.3, 200],
         [299.7, 200, 279.7, 200.0]]
    )  # fmt: skip
    d = np.zeros((4, 128), dtype=np.uint8)
    d[0, :16] = 30  # distance 30 * 4 = 120 from landmark 0
    d[1, :16] = 40  # 160: ratio 0.75
    d[2:] = 200
    d[2, :16] = 170  # 120 from landmark 1
    d[3, :16] = 160  # 160
    kw = {"gate_chi2": 18.47, "max_distance": 350.0}
    both = associate(_prediction(z), desc_lm, z_obs, d, ratio=0.8, **kw)
    none = associate(_prediction(z), desc_lm, z_obs, d, ratio=0.7, **kw)
    mixed = associate(_prediction(z), desc_lm, z_obs, d, ratio=np.array([0.8, 0.7]), **kw)
    assert list(both.pred_index) == [0, 1] and list(both.match_index) == [0, 2]
    assert len(none.pred_index) == 0
    assert list(mixed.pred_index) == [0] and list(mixed.match_index) == [0]


def test_another_vehicles_landmark_must_be_distinct_in_the_whole_frame():
    """A look-alike alone in its landmark's window, its twin (as close in descriptor) far
    outside: the ratio test over the window has nothing to compare it with and takes it;
    over the frame (`frame_wide`) it is refused. A distinct match is kept either way, and
    `frame_wide` per landmark applies to its landmarks only."""
    z = np.array([[100, 100, 90, 100], [300, 200, 280, 200.0]])
    desc_lm = np.zeros((2, 128), dtype=np.uint8)
    desc_lm[1, :] = 200
    z_obs = np.array(
        [[100.3, 100, 90.3, 100], [600, 300, 590, 300], [300.3, 200, 280.3, 200],
         [50, 50, 40, 50.0]]
    )  # fmt: skip
    d = np.zeros((4, 128), dtype=np.uint8)
    d[0, :16] = 30  # 120 from landmark 0, alone in its window ...
    d[1, :16] = 31  # ... and its twin across the image: 124
    d[2] = 200
    d[2, :16] = 170  # 120 from landmark 1; nothing else within 200 of it
    d[3, :] = 100
    kw = {"gate_chi2": 18.47, "ratio": 0.7, "max_distance": 350.0}
    window = associate(_prediction(z), desc_lm, z_obs, d, **kw)
    frame = associate(_prediction(z), desc_lm, z_obs, d, frame_wide=True, **kw)
    per = associate(_prediction(z), desc_lm, z_obs, d, frame_wide=np.array([False, True]), **kw)
    assert list(window.pred_index) == [0, 1] and list(window.match_index) == [0, 2]
    assert list(frame.pred_index) == [1] and list(frame.match_index) == [2]
    assert list(per.pred_index) == [0, 1]
    per = associate(_prediction(z), desc_lm, z_obs, d, frame_wide=np.array([True, False]), **kw)
    assert list(per.pred_index) == [1]


def test_descriptor_tests_ask_more_of_another_vehicles_landmark():
    """The stricter ratio, and with `other_over_frame` the frame-wide second-best, for the
    landmarks the observing vehicle never observed; its own keep the window's ratio."""
    book = LandmarkBook(2)
    view = np.tile([0.0, 0.0, -1.0], (3, 1))
    ids = book.add(np.zeros((3, 128), dtype=np.uint8), 0, 5, np.full(3, -1), view)
    book.last_seen_ns[ids[:2], 1] = 5  # vehicle 1 saw the first two
    ratio, wide = descriptor_tests(book, ids, 1, 0.8, 0.7, True)
    assert list(ratio) == [0.8, 0.8, 0.7] and list(wide) == [False, False, True]
    ratio, wide = descriptor_tests(book, ids, 1, 0.8, 0.7, False)
    assert list(ratio) == [0.8, 0.8, 0.7] and not wide.any()
    ratio, wide = descriptor_tests(book, ids, 0, 0.8, 0.7, True)
    assert list(ratio) == [0.8] * 3 and not wide.any()


def test_another_vehicles_landmark_in_a_wide_window_must_lie_closer():
    """`lookalike_gates`: a landmark the vehicle never observed keeps the gate while its
    window is small and gets a tighter one, by the log of the window's area, once a
    look-alike is likelier there than the landmark itself; its own landmarks, and every
    landmark without a bound, keep the gate. `associate` then refuses a match inside the
    gate but beyond the landmark's own, and that match still starts no landmark."""
    book = LandmarkBook(2)
    view = np.tile([0.0, 0.0, -1.0], (4, 1))
    ids = book.add(np.zeros((4, 128), dtype=np.uint8), 0, 5, np.full(4, -1), view)
    book.last_seen_ns[ids[:2], 1] = 5  # vehicle 1 observed the first two
    sigma = np.array([0.5, 8.0, 0.5, 8.0])  # px: narrow, wide, narrow, wide windows
    S = np.eye(4)[None] * sigma[:, None, None] ** 2
    bound = lookalike_bound(50.0)
    assert bound == pytest.approx(-2 * np.log(2 * np.pi * 50e-6))
    gates = lookalike_gates(book, ids, 1, S, 18.47, bound)
    # own: the gate; another's, narrow (ln det S_l = 4 ln 0.5 < 0): the gate; wide: tighter
    assert list(gates[:3]) == [18.47] * 3
    assert gates[3] == pytest.approx(bound - 4 * np.log(8.0))
    assert 0 < gates[3] < 18.47
    assert list(lookalike_gates(book, ids, 1, S, 18.47, lookalike_bound(0.0))) == [18.47] * 4
    assert list(lookalike_gates(book, ids, 0, S, 18.47, bound)) == [18.47] * 4  # all its own

    # one landmark (new to the vehicle, wide window), one match 20 px off in both images:
    # d2 = 2 (20 / 8)^2 = 12.5, inside the gate, beyond the bound (16.1 - 8.3)
    pred = _prediction(np.array([[300.0, 200, 280, 200]]), sigma=8.0)
    z_obs = np.array([[320.0, 200, 300, 200]])
    desc = np.zeros((1, 128), dtype=np.uint8)
    kw = {"gate_chi2": 18.47, "ratio": 0.8, "max_distance": 350.0}
    assert list(associate(pred, desc, z_obs, desc, **kw).pred_index) == [0]
    refused = associate(pred, desc, z_obs, desc, accept_chi2=gates[3:], **kw)
    assert len(refused.pred_index) == 0 and list(refused.near_landmark) == [True]


def test_spread_order_visits_every_cell_before_repeating():
    uv = np.column_stack([RNG.uniform(0, 400, 200), RNG.uniform(0, 400, 200)])
    prio = RNG.uniform(size=200)
    order = spread_order(uv, prio, (400, 400), grid=4)
    assert sorted(order) == list(range(200))
    cells = (uv[order, 1] // 100).astype(int) * 4 + (uv[order, 0] // 100).astype(int)
    assert len(set(cells[:16])) == 16
    # within a cell, lower priority first
    c0 = order[cells == cells[0]]
    assert np.all(np.diff(prio[c0]) >= 0)


def test_classify_defines_the_three_types():
    """Associated with a landmark the vehicle saw before: 1 (a loop closure when it was
    absent longer than the gap); associated with one it never saw: 2; inside no window and
    not associated: 3; inside a window but not associated: 0 (neither updates nor maps)."""
    s = 1_000_000_000
    near = np.array([True, True, True, False, True, False])
    rows = np.array([2, 0, 4])
    last_seen = np.array([95 * s, NEVER, 60 * s])
    types = classify(near, rows, last_seen, 100 * s, loop_gap_ns=20 * s)
    assert list(types.type) == [TYPE_2, 0, TYPE_1, TYPE_3, TYPE_1, TYPE_3]
    assert list(types.absent_ns) == [5 * s, 0, 40 * s]
    assert list(types.loop_closure) == [False, False, True]
    assert (types.count(TYPE_1), types.count(TYPE_2), types.count(TYPE_3)) == (2, 1, 2)
    assert list(unassociated(3).type) == [TYPE_3] * 3
    assert list(classify(near).type) == [0, 0, 0, TYPE_3, 0, TYPE_3]


def test_noise_scale_flags_the_landmarks_another_vehicle_has_observed():
    """The factor goes to a vehicle's observations of landmarks another vehicle has observed
    (mapped by it, or seen by it since); a landmark only this vehicle has observed keeps the
    filter's noise; a factor of 1 (the setting off) flags nothing."""
    book = LandmarkBook(3)
    down = np.tile([0.0, 0.0, -1.0], (4, 1))
    ids = book.add(np.zeros((4, 128), np.uint8), 0, 10, np.full(4, -1), down)  # vehicle 0's
    book.observe(ids[2:3], 1, 20, down[:1], np.array([10.0]))  # vehicle 1 sees 2 too
    np.testing.assert_array_equal(noise_scale(book, ids, 0, 4.0), [1.0, 1.0, 4.0, 1.0])
    np.testing.assert_array_equal(noise_scale(book, ids, 1, 4.0), [4.0, 4.0, 4.0, 4.0])
    np.testing.assert_array_equal(noise_scale(book, ids, 2, 4.0), [4.0] * 4)
    assert noise_scale(book, ids, 1, 1.0) is None
    ratio = SlamSettings(pixel_sigma_px=0.35, other_vehicle_pixel_sigma_px=0.7)
    assert ratio.other_vehicle_noise_ratio == 4.0
    assert SlamSettings(pixel_sigma_px=0.35).other_vehicle_noise_ratio == 1.0  # 0: off
    assert SlamSettings(other_vehicle_pixel_sigma_px=0.3).other_vehicle_noise_ratio == 1.0


def test_landmark_errors_given_the_vehicle_are_the_schur_complement():
    """G = P_mv P_vv^-1 and the rest's covariance P_mm - P_mv P_vv^-1 P_vm, per landmark, as
    the dense conditional of the joint Gaussian gives them."""
    n_v, k, d = 5, 4, 3
    A = RNG.normal(size=(n_v + k * d, n_v + k * d))
    P = A @ A.T + 0.1 * np.eye(n_v + k * d)
    P_vv = P[:n_v, :n_v]
    P_vm = np.stack([P[:n_v, n_v + j * d : n_v + (j + 1) * d] for j in range(k)])
    P_mm = np.stack([P[n_v + j * d :, n_v + j * d :][:d, :d] for j in range(k)])
    G_all, cov_all = LandmarkErrors(P_vm, P_mm).given_vehicle(P_vv, np.arange(k))
    for j in range(k):
        c = slice(n_v + j * d, n_v + (j + 1) * d)
        G = P[c, :n_v] @ np.linalg.inv(P_vv)
        np.testing.assert_allclose(G_all[j], G, atol=1e-10)
        np.testing.assert_allclose(cov_all[j], P[c, c] - G @ P[:n_v, c], atol=1e-10)
    G_alone, cov_alone = LandmarkErrors.independent(P_mm, n_v).given_vehicle(P_vv, np.arange(k))
    assert G_alone.shape == (k, d, n_v) and not G_alone.any()
    np.testing.assert_array_equal(cov_alone, P_mm)


def test_the_one_correction_test_knows_what_a_landmark_shares_with_the_vehicle():
    """Landmarks mapped from the vehicle's pose carry its error (here 0.2 m, theirs 1 cm):
    their innovations are small whatever that error, so a look-alike 6 px off stands out.
    Taken as independent of the vehicle (their marginals of 0.2 m), it hides in the windows."""
    rng = np.random.default_rng(5)
    k, n_v = 8, 3
    # a rectified pair (f 500 px, baseline 0.5 m) seeing points 8-12 m ahead: d(u_l, v_l,
    # u_r, v_r) / d(point), 40-60 px per metre
    f, b = 500.0, 0.5
    X, Y, Z = rng.uniform(-3, 3, k), rng.uniform(-2, 2, k), rng.uniform(8, 12, k)
    zero, one = np.zeros(k), np.ones(k)
    H_m = (f / Z)[:, None, None] * np.stack(
        [
            np.stack([one, zero, -X / Z], axis=1),
            np.stack([zero, one, -Y / Z], axis=1),
            np.stack([one, zero, -(X - b) / Z], axis=1),
            np.stack([zero, one, -Y / Z], axis=1),
        ],
        axis=1,
    )
    H_v = -H_m  # the pixels follow the landmark relative to the vehicle
    P_vv = 0.2**2 * np.eye(3)
    P_vm = np.broadcast_to(P_vv, (k, 3, 3)).copy()  # dm_j = dx + e_j
    P_mm = P_vm + 0.01**2 * np.eye(3)
    dx = rng.normal(0.0, 0.2, 3)
    e = rng.normal(0.0, 0.01, (k, 3))
    R = 0.5**2 * np.eye(4)
    nu = (H_v @ dx) + np.einsum("kij,kj->ki", H_m, dx + e) + rng.normal(0.0, 0.5, (k, 4))
    nu[3] += 6.0  # a look-alike, 6 px along the image's diagonal in both images
    pred = LandmarkPrediction(np.arange(k), np.zeros((k, 4)), H_v, H_m, np.zeros((k, 4, 4)))
    rows = np.arange(k)
    chi2 = 18.47  # 4 dof, 0.999
    shared = pose_consistent(pred, rows, nu, P_vv, LandmarkErrors(P_vm, P_mm), R, chi2)
    assert shared.tolist() == [j != 3 for j in range(k)]
    apart = pose_consistent(pred, rows, nu, P_vv, LandmarkErrors.independent(P_mm, n_v), R, chi2)
    assert apart.all()
