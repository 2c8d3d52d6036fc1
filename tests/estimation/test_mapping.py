"""The landmark book: observations, viewing directions, the eviction order."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.mapping import NEVER, LandmarkBook

TEN_M = 10.0  # the distance of an observation (m), where the test does not look at it


def _book(n_landmarks: int, n_vehicles: int = 2) -> LandmarkBook:
    book = LandmarkBook(n_vehicles, capacity=2)  # grows
    desc = np.zeros((n_landmarks, 128), dtype=np.uint8)
    views = np.tile([0.0, 0.0, -1.0], (n_landmarks, 1))
    book.add(desc, 0, 100, np.full(n_landmarks, -1), views, np.full(n_landmarks, TEN_M))
    return book


def test_eviction_order_protected_never_fewest_observations_first_then_largest_covariance():
    book = _book(6)
    book.observe(np.array([1, 2, 3]), 0, 200, np.tile([0.0, 0.0, -1.0], (3, 1)), TEN_M)
    book.observe(np.array([2]), 0, 300, np.array([[0.0, 0.0, -1.0]]), TEN_M)
    trace = np.array([1.0, 2.0, 3.0, 9.0, 0.5, 4.0])
    order = book.eviction_order(np.array([5]), trace, np.array([NEVER, NEVER]))
    # slot 5 protected; seen once: 0 (trace 1), 4 (0.5) -> the larger first; twice: 3 (9), 1 (2)
    assert list(order) == [0, 4, 3, 1, 2]


def test_landmarks_another_vehicle_tracks_go_last():
    book = _book(4)
    # vehicle 1 observed landmarks 0 and 1 in its latest frame (t = 500)
    book.observe(np.array([0, 1]), 1, 500, np.tile([0.0, 0.0, -1.0], (2, 1)), TEN_M)
    book.observe(np.array([2]), 1, 400, np.array([[0.0, 0.0, -1.0]]), TEN_M)
    order = book.eviction_order(np.zeros(0, np.int64), np.ones(4), np.array([NEVER, 500]))
    assert list(order[-2:]) == [0, 1] and set(order[:2]) == {2, 3}
    assert list(order[:2]) == [3, 2]  # fewer observations first


def test_landmarks_another_vehicle_observed_within_its_tracking_window_go_last():
    book = _book(4)
    # vehicle 1's latest frame is at t = 500: landmark 0 observed then, 1 at 300 and 2 at 100
    # (each twice now), 3 never by it
    for lm, t in ((0, 500), (1, 300), (2, 100)):
        book.observe(np.array([lm]), 1, t, np.array([[0.0, 0.0, -1.0]]), TEN_M)
    latest = np.array([NEVER, 500])
    # the latest frame only: 1 and 2 go with 3 (3 has fewer observations: first)
    assert list(book.eviction_order(np.zeros(0, np.int64), np.ones(4), latest)) == [3, 1, 2, 0]
    # observed within 250 of the latest frame: 1 is tracked too; 2 (400 before) is not
    order = book.eviction_order(np.zeros(0, np.int64), np.ones(4), latest, tracking_ns=250)
    assert list(order[:2]) == [3, 2] and set(order[2:]) == {0, 1}
    # the vehicle evicting (NEVER) protects nothing by its own observations
    own = book.eviction_order(np.zeros(0, np.int64), np.ones(4), np.array([NEVER, NEVER]), 10**9)
    assert list(own) == [3, 0, 1, 2]


def test_viewing_angle_limit_and_other_observers():
    book = _book(2)
    book.observe(np.array([1]), 1, 200, np.array([[0.0, 0.0, -1.0]]), TEN_M)
    tilted = np.array([[np.sin(1.0), 0.0, -np.cos(1.0)], [0.0, np.sin(1.5), -np.cos(1.5)]])
    assert list(book.ids_seen_from(np.array([0, 1]), tilted, np.cos(1.2))) == [True, False]
    assert book.other_observers(np.array([0, 1]), 0, ["uav1", "uav2"]) == "uav2"
    assert book.other_observers(np.array([0]), 0, ["uav1", "uav2"]) == ""
    assert book.archive(["uav1", "uav2"], "cartesian").observers() == ("uav1", "uav1;uav2")


def test_another_vehicles_landmark_is_looked_for_from_about_its_distance():
    book = _book(3)  # vehicle 0 observed them from 10 m (`_book`), landmark 2 from no distance
    book.observe(np.array([1]), 0, 200, np.array([[0.0, 0.0, -1.0]]), np.array([40.0]))
    ids = np.array([0, 0, 0, 1, 1])
    # vehicle 1 never observed them: within 4x of 10 m, and of 20 m for landmark 1 (the
    # geometric mean of 10 and 40)
    at = np.array([30.0, 50.0, 2.0, 70.0, 90.0])
    assert book.ids_within_distance(ids, 1, at, 4.0).tolist() == [True, False, False, True, False]
    assert book.ids_within_distance(ids, 1, at, 0.0).all()  # 0: no limit
    assert book.ids_within_distance(ids, 0, at, 4.0).all()  # its own: from any distance
    book.observe(np.array([0]), 1, 300, np.array([[0.0, 0.0, -1.0]]), np.array([45.0]))
    assert book.ids_within_distance(np.array([0]), 1, np.array([500.0]), 4.0).all()  # seen now
    unknown = book.add(np.zeros((1, 128), np.uint8), 0, 0, np.array([-1]), np.zeros((1, 3)))
    assert book.ids_within_distance(unknown, 1, np.array([1e4]), 4.0).all()  # a prior map's


def test_evicted_landmarks_keep_their_gaussian_and_come_back_in_the_archive():
    book = _book(3)
    cov = np.stack([np.diag([1.0, 2.0, 3.0]) * (i + 1) for i in range(3)])
    book.store_estimates(np.arange(3), np.arange(9.0).reshape(3, 3), cov)
    book.evict(np.array([1]), np.array([[7.0, 8.0, 9.0]]), 5 * cov[1:2], 400)
    book.keep_slots(np.array([0, 2]))
    a = book.archive(["uav1", "uav2"], "inverse_depth")
    assert list(a.in_state) == [True, False, True] and list(a.evicted_ns) == [NEVER, 400, NEVER]
    np.testing.assert_array_equal(a.p_nav_m[1], [7.0, 8.0, 9.0])
    np.testing.assert_array_equal(a.cov_nav_m2[1], 5 * cov[1])
    np.testing.assert_allclose(a.landmark_map().std_m[1], np.sqrt(5 * np.diag(cov[1])))
    book.readmit(np.array([1]))
    assert list(book.slot_ids) == [0, 2, 1] and list(book.reactivations[:3]) == [0, 1, 0]


def test_vehicles_are_grouped_by_the_landmarks_they_observed():
    """A group is the vehicles linked by landmarks they both observed, directly or through
    others (the team's gauges, gauge.py); until then each vehicle is a group of its own."""
    book = LandmarkBook(4)
    desc = np.zeros((2, 128), dtype=np.uint8)
    views = np.tile([0.0, 0.0, -1.0], (2, 1))
    a = book.add(desc, 0, 100, np.full(2, -1), views, np.full(2, TEN_M))  # vehicle 0's
    b = book.add(desc, 2, 100, np.full(2, -1), views, np.full(2, TEN_M))  # vehicle 2's
    assert [book.group(1 << i) for i in range(4)] == [0b0001, 0b0010, 0b0100, 0b1000]
    book.observe(a[:1], 1, 200, views[:1], TEN_M)  # vehicle 1 sees one of vehicle 0's
    assert book.group(0b0001) == book.group(0b0010) == 0b0011
    assert book.group(0b0100) == 0b0100 and book.group(0b1000) == 0b1000
    assert book.group(int(book.observers[a[1]])) == 0b0011  # seen by 0 alone: 0's group
    book.observe(b[1:], 1, 300, views[:1], TEN_M)  # and one of vehicle 2's: one group of three
    assert {book.group(1 << i) for i in range(3)} == {0b0111}
    assert book.group(0b1000) == 0b1000
    assert book.group(0) == 0b1111  # no observer (a prior map's landmark): the whole team
