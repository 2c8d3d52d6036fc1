"""The landmark archive: every landmark a `fuse` run ever mapped, evicted ones too, with what
a later run needs to use it again (its nav-frame Gaussian, descriptor, observers and times).
`map.npz` stores it (`io/map_file.py`, docs/fuse_outputs.md); `LandmarkMap` (map.csv,
map.ply) is its summary (`landmark_map`).

What is known of a landmark's correlation with the trajectory: nothing is kept. A landmark
in the state at the end of the run is correlated with every pose and landmark there, and an
evicted one was when it left the state; marginalising it out of the filter dropped those
cross-covariances (the price of a bounded state), and the archive stores the marginal only.
A user of the archive must therefore treat a landmark's error as correlated with the
trajectory by an unknown amount (re-activation in the same run does: `estimation/
reactivation.py`), never as independent of it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, U8, BoolArray, check_shape
from cvslam_cli.records.features import DESCRIPTOR_SIZE
from cvslam_cli.records.landmarks import LandmarkMap

NEVER_NS = int(np.iinfo(np.int64).min)
"""A stamp meaning "never" (`last_seen_ns` of a vehicle that did not see the landmark,
`evicted_ns` of one never evicted)."""


@dataclass(frozen=True, eq=False)
class LandmarkArchive:
    """N landmarks seen by V vehicles, nav frame (NED), metres, stamps in ns:

    - `vehicles` V names: the columns of `last_seen_ns`;
    - `landmark_id` (N,) int64, unique; `true_id` (N,) int64 as in `LandmarkMap`;
    - `p_nav_m` (N, 3) float64 and `cov_nav_m2` (N, 3, 3) float64: the landmark's last
      estimate and its marginal covariance in the nav frame (at the end of the run for one
      still in the state, else when it was last evicted), whatever coordinates the filter
      wrote it in;
    - `descriptor` (N, 128) uint8: the SIFT descriptor of the frame that created it;
    - `view_dir_sum_nav` (N, 3) float64: the sum of the unit vectors from the landmark to
      the cameras that observed it (its mean viewing direction; `mapping.py`);
    - `first_seen_ns` (N,) int64; `last_seen_ns` (N, V) int64 per vehicle (`NEVER_NS`:
      never); `n_observations` (N,) int64 observations used;
    - `in_state` (N,) bool at the end; `evicted_ns` (N,) int64 its last eviction
      (`NEVER_NS`: never evicted); `reactivations` (N,) int64 times it was brought back;
    - `coordinates`: how the filter wrote landmarks in its state ("cartesian",
      "inverse_depth"; the stored Gaussians are nav-frame either way);
    - `session` (N,) int64: the mapping session that created the landmark (0: the first;
      a run started from a prior map, `estimation/prior_map.py`, keeps the prior's and
      numbers its own landmarks one more than the prior's largest). None: all 0;
    - `batch` (N,) bool: the landmark's estimate and covariance are a batch solution's
      (`cvslam refine`: the marginal of one joint solution over every pose and landmark)
      rather than a filter's (`cvslam fuse`: the marginal when it was last evicted or at
      the end, the correlations a bounded state dropped, module docstring). None: all
      false.
    """

    vehicles: tuple[str, ...]
    landmark_id: I64
    true_id: I64
    p_nav_m: F64
    cov_nav_m2: F64
    descriptor: U8
    view_dir_sum_nav: F64
    first_seen_ns: I64
    last_seen_ns: I64
    n_observations: I64
    in_state: BoolArray
    evicted_ns: I64
    reactivations: I64
    coordinates: str
    session: I64 | None = None
    batch: BoolArray | None = None

    def __post_init__(self) -> None:
        vehicles = tuple(self.vehicles)
        if not all(isinstance(v, str) and v for v in vehicles):
            raise ValueError("LandmarkArchive.vehicles: expected non-empty vehicle names")
        object.__setattr__(self, "vehicles", vehicles)
        dims: dict[str, int] = {"V": len(vehicles), "D": DESCRIPTOR_SIZE}

        def check(name: str, shape: tuple[int | str, ...], kind: str, dtype: type) -> None:
            arr = check_shape(f"LandmarkArchive.{name}", getattr(self, name), shape, kind, dims)
            object.__setattr__(self, name, np.ascontiguousarray(arr.astype(dtype)))

        check("landmark_id", ("N",), "iu", np.int64)
        check("true_id", ("N",), "iu", np.int64)
        check("p_nav_m", ("N", 3), "iuf", np.float64)
        check("cov_nav_m2", ("N", 3, 3), "iuf", np.float64)
        check("descriptor", ("N", "D"), "iu", np.uint8)
        check("view_dir_sum_nav", ("N", 3), "iuf", np.float64)
        check("first_seen_ns", ("N",), "iu", np.int64)
        check("last_seen_ns", ("N", "V"), "iu", np.int64)
        check("n_observations", ("N",), "iu", np.int64)
        check("in_state", ("N",), "b", np.bool_)
        check("evicted_ns", ("N",), "iu", np.int64)
        check("reactivations", ("N",), "iu", np.int64)
        if self.session is None:
            object.__setattr__(self, "session", np.zeros(len(self.landmark_id), dtype=np.int64))
        check("session", ("N",), "iu", np.int64)
        if self.batch is None:
            object.__setattr__(self, "batch", np.zeros(len(self.landmark_id), dtype=bool))
        check("batch", ("N",), "b", np.bool_)
        if len(np.unique(self.landmark_id)) != len(self.landmark_id):
            raise ValueError("LandmarkArchive.landmark_id: ids must be unique")
        if not isinstance(self.coordinates, str):
            raise ValueError("LandmarkArchive.coordinates: expected a string")

    def __len__(self) -> int:
        return len(self.landmark_id)

    def observers(self) -> tuple[str, ...]:
        """Per landmark, the vehicles that observed it, joined with ';' (`LandmarkMap`)."""
        seen = self.last_seen_ns != NEVER_NS
        return tuple(
            ";".join(v for v, s in zip(self.vehicles, row, strict=True) if s) for row in seen
        )

    def landmark_map(self) -> LandmarkMap:
        """The summary map.csv / map.ply store."""
        n = len(self)
        std = np.sqrt(np.maximum(np.diagonal(self.cov_nav_m2, axis1=1, axis2=2), 0.0))
        last = self.last_seen_ns.max(axis=1) if n else np.zeros(0, dtype=np.int64)
        return LandmarkMap(
            landmark_id=self.landmark_id,
            p_nav_m=self.p_nav_m,
            std_m=std.reshape(n, 3),
            observers=self.observers(),
            n_observations=self.n_observations,
            first_seen_ns=self.first_seen_ns,
            last_seen_ns=last,
            in_state=self.in_state,
            true_id=self.true_id,
            session=self.session,
        )


def merge_archives(archives: Sequence[LandmarkArchive]) -> LandmarkArchive:
    """One archive from runs of separate filters (`fuse --single`): landmarks side by side,
    ids renumbered in order, the vehicles the union (in first-seen order)."""
    vehicles: list[str] = []
    for a in archives:
        vehicles += [v for v in a.vehicles if v not in vehicles]
    if not vehicles:
        raise ValueError("merge_archives: no archive to merge")
    last = []
    for a in archives:
        col = np.full((len(a), len(vehicles)), NEVER_NS, dtype=np.int64)
        col[:, [vehicles.index(v) for v in a.vehicles]] = a.last_seen_ns
        last.append(col)
    coords = {a.coordinates for a in archives}

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(a, name) for a in archives])

    return LandmarkArchive(
        vehicles=tuple(vehicles),
        landmark_id=np.arange(sum(len(a) for a in archives)),
        true_id=cat("true_id"),
        p_nav_m=cat("p_nav_m"),
        cov_nav_m2=cat("cov_nav_m2"),
        descriptor=cat("descriptor"),
        view_dir_sum_nav=cat("view_dir_sum_nav"),
        first_seen_ns=cat("first_seen_ns"),
        last_seen_ns=np.concatenate(last),
        n_observations=cat("n_observations"),
        in_state=cat("in_state"),
        evicted_ns=cat("evicted_ns"),
        reactivations=cat("reactivations"),
        session=cat("session"),
        batch=cat("batch"),
        coordinates=coords.pop() if len(coords) == 1 else ";".join(sorted(coords)),
    )
