"""The landmark map: every landmark a `fuse` run mapped, as the filter gives it and as
`map.csv` / `map.ply` / `result.mcap` store it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, BoolArray, check_shape

UNKNOWN_TRUE_ID = -1
"""`true_id` of a landmark whose simulator id is not known (real data, or a file without it)."""


@dataclass(frozen=True, eq=False)
class LandmarkMap:
    """The landmark map at the end of `fuse`, N landmarks, nav frame (NED), metres.

    - `landmark_id` (N,) int64, unique;
    - `p_nav_m` (N, 3) float64 position;
    - `std_m` (N, 3) float64 standard deviations (sqrt of the covariance diagonal);
    - `observers` N strings: the vehicles that observed the landmark, joined with ';'
      (e.g. "uav1;uav2");
    - `n_observations` (N,) int64 observations used;
    - `first_seen_ns`, `last_seen_ns` (N,) int64 stamps of the first and last observation;
    - `in_state` (N,) bool: still in the filter state at the end (False: evicted earlier);
    - `true_id` (N,) int64: the simulator's id of the stereo match that created the landmark,
      `UNKNOWN_TRUE_ID` (-1) unknown, -2 an outlier the simulator injected;
    - `session` (N,) int64: the mapping session that created it (`LandmarkArchive.session`;
      None: all 0, one session).

    Arrays are converted to these dtypes; a wrong shape or kind is a ValueError.
    """

    landmark_id: I64
    p_nav_m: F64
    std_m: F64
    observers: tuple[str, ...]
    n_observations: I64
    first_seen_ns: I64
    last_seen_ns: I64
    in_state: BoolArray
    true_id: I64
    session: I64 | None = None

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}

        def check(name: str, shape: tuple[int | str, ...], kind: str, dtype: type) -> None:
            arr = check_shape(f"LandmarkMap.{name}", getattr(self, name), shape, kind, dims)
            object.__setattr__(self, name, arr.astype(dtype))

        check("landmark_id", ("N",), "iu", np.int64)
        n = dims["N"]
        check("p_nav_m", ("N", 3), "iuf", np.float64)
        check("std_m", ("N", 3), "iuf", np.float64)
        for name in ("n_observations", "first_seen_ns", "last_seen_ns"):
            check(name, ("N",), "iu", np.int64)
        check("in_state", ("N",), "b", np.bool_)
        check("true_id", ("N",), "iu", np.int64)
        if self.session is None:
            object.__setattr__(self, "session", np.zeros(n, dtype=np.int64))
        check("session", ("N",), "iu", np.int64)
        observers = tuple(self.observers)
        if len(observers) != n or not all(isinstance(o, str) for o in observers):
            raise ValueError(
                f"LandmarkMap.observers: expected {n} strings (one per landmark), "
                f"got {len(observers)} items"
            )
        object.__setattr__(self, "observers", observers)
        if len(np.unique(self.landmark_id)) != n:
            ids_sorted = np.sort(self.landmark_id)
            dup = int(ids_sorted[np.flatnonzero(np.diff(ids_sorted) == 0)[0]])
            raise ValueError(f"LandmarkMap.landmark_id: id {dup} appears more than once")

    def __len__(self) -> int:
        return len(self.landmark_id)

    @property
    def max_std_m(self) -> F64:
        """(N,) the largest of the three standard deviations of each landmark."""
        return self.std_m.max(axis=1) if len(self) else np.zeros(0)
