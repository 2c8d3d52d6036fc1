"""The landmark book: observations, viewing directions, the eviction order."""

from __future__ import annotations

import numpy as np

from cvslam_cli.estimation.mapping import NEVER, LandmarkBook


def _book(n_landmarks: int, n_vehicles: int = 2) -> LandmarkBook:
    book = LandmarkBook(n_vehicles, capacity=2)  # grows
    desc = np.zeros((n_landmarks, 128), dtype=np.uint8)
    views = np.tile([0.0, 0.0, -1.0], (n_landmarks, 1))
    book.add(desc, 0, 100, np.full(n_landmarks, -1), views)
    return book


def test_eviction_order_protected_never_fewest_observations_first_then_largest_covariance():
    book = _book(6)
    book.observe(np.array([1, 2, 3]), 0, 200, np.tile([0.0, 0.0, -1.0], (3, 1)))
    book.observe(np.array([2]), 0, 300, np.array([[0.0, 0.0, -1.0]]))
    trace = np.array([1.0, 2.0, 3.0, 9.0, 0.5, 4.0])
    order = book.eviction_order(np.array([5]), trace, np.array([NEVER, NEVER]))
    # slot 5 protected; seen once: 0 (trace 1), 4 (0.5) -> the larger first; twice: 3 (9), 1 (2)
    assert list(order) == [0, 4, 3, 1, 2]


def test_landmarks_another_vehicle_tracks_go_last():
    book = _book(4)
    # vehicle 1 observed landmarks 0 and 1 in its latest frame (t = 500)
    book.observe(np.array([0, 1]), 1, 500, np.tile([0.0, 0.0, -1.0], (2, 1)))
    book.observe(np.array([2]), 1, 400, np.array([[0.0, 0.0, -1.0]]))
    order = book.eviction_order(np.zeros(0, np.int64), np.ones(4), np.array([NEVER, 500]))
    assert list(order[-2:]) == [0, 1] and set(order[:2]) == {2, 3}
    assert list(order[:2]) == [3, 2]  # fewer observations first


def test_viewing_angle_limit_and_other_observers():
    book = _book(2)
    book.observe(np.array([1]), 1, 200, np.array([[0.0, 0.0, -1.0]]))
    tilted = np.array([[np.sin(1.0), 0.0, -np.cos(1.0)], [0.0, np.sin(1.5), -np.cos(1.5)]])
    assert list(book.seen_from(np.array([0, 1]), tilted, np.cos(1.2))) == [True, False]
    assert book.other_observers(np.array([0, 1]), 0, ["uav1", "uav2"]) == "uav2"
    assert book.other_observers(np.array([0]), 0, ["uav1", "uav2"]) == ""
    assert book.observer_names(["uav1", "uav2"]) == ("uav1", "uav1;uav2")
