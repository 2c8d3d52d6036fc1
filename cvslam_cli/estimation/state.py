"""The joint state of the central filter: every vehicle's block, then every landmark in the
state (paper eq. 3 and section "Cooperative VSLAM"):

    X = [X_v1 ... X_vM, m_1 ... m_L],   P (n, n),   n = sum(n_vi) + 3 L

Vehicle blocks come first and keep their place; landmark j occupies rows
`n_vehicles + 3 j : n_vehicles + 3 j + 3`. The structure the filter exploits:

- predict (eq. 1, 2) touches one vehicle block only: landmarks are static and the other
  vehicles unchanged, so with the vehicle's transition F and process noise Q over an interval
      P_vv <- F P_vv F^T + Q,    P_vo <- F P_vo    (o: every other state)
  costs O(n n_v), not O(n^3);
- an observation touches one vehicle and the landmarks it sees (H's non-zero columns), so the
  update costs O(n^2 m) (`filters.py`);
- adding a landmark appends 3 rows/columns, removing landmarks deletes theirs (Gaussian
  marginalisation).

x and P are views of storage with room to grow (capacity doubles when full). The
measurement update works on that storage in place (`filters.ekf_update_inplace`,
`filters.hinf_update_inplace`) with persistent work buffers of the same capacity, so an
update allocates no n x n array.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.estimation.filters import FilterSettings, GammaPolicy, UpdateResult, update_inplace
from cvslam_cli.estimation.motion.models import MotionModel
from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True)
class VehicleBlock:
    name: str
    model: MotionModel
    start: int

    @property
    def index(self) -> I64:
        return np.arange(self.start, self.start + self.model.n)


class JointState:
    """Mean `x` (n,) and covariance `P` (n, n) of all vehicles and the landmarks in the state."""

    def __init__(self, blocks: list[tuple[str, MotionModel, F64, F64]]) -> None:
        """blocks: (vehicle name, motion model, x0 (n_v,), P0 (n_v, n_v)) per vehicle."""
        self.vehicles: dict[str, VehicleBlock] = {}
        start = 0
        for name, model, _, _ in blocks:
            self.vehicles[name] = VehicleBlock(name, model, start)
            start += model.n
        self.n_vehicle_states = start
        # storage with room to grow: x and P are views of the first n entries
        self._n = start
        self._x = np.zeros(start + 3 * 64)
        self._P = np.zeros((len(self._x), len(self._x)))
        # scratch space of the in-place update, 2 capacity^2 entries: the first 2 n^2 as two
        # contiguous (n, n) arrays (np.empty: pages the filter never uses are never touched)
        self._work = np.empty(2 * len(self._x) ** 2)
        self.x = np.concatenate([np.asarray(b[2], dtype=float) for b in blocks])
        # P stays exactly symmetric: every change writes both triangles alike (the in-place
        # NH-infinity update relies on it and skips the 0.5 (P + P^T) pass)
        for (_, _, _, P0), vb in zip(blocks, self.vehicles.values(), strict=True):
            P0 = np.asarray(P0, dtype=float)
            self.P[np.ix_(vb.index, vb.index)] = 0.5 * (P0 + P0.T)

    @property
    def x(self) -> F64:
        """(n,) state mean (a view)."""
        return self._x[: self._n]

    @x.setter
    def x(self, value: F64) -> None:
        self._x[: self._n] = value

    @property
    def P(self) -> F64:
        """(n, n) state covariance (a view)."""
        return self._P[: self._n, : self._n]

    @P.setter
    def P(self, value: F64) -> None:
        self._P[: self._n, : self._n] = value

    def _reserve(self, n: int) -> None:
        cap = len(self._x)
        if n <= cap:
            return
        new_cap = max(n, 2 * cap)
        x = np.zeros(new_cap)
        P = np.zeros((new_cap, new_cap))
        x[: self._n] = self.x
        P[: self._n, : self._n] = self.P
        self._x, self._P = x, P
        self._work = np.empty(2 * new_cap**2)

    def _work_view(self) -> F64:
        n = self._n
        return self._work[: 2 * n * n].reshape(2, n, n)

    @property
    def n(self) -> int:
        return self._n

    @property
    def n_landmarks(self) -> int:
        return (self._n - self.n_vehicle_states) // 3

    def landmark_index(self, slots: I64) -> I64:
        """State rows of the landmarks in `slots` (k,) -> (k, 3)."""
        return self.n_vehicle_states + 3 * np.asarray(slots, dtype=np.int64)[:, None] + np.arange(3)

    def landmarks(self) -> F64:
        """(L, 3) landmark positions, nav frame."""
        return self.x[self.n_vehicle_states :].reshape(-1, 3)

    def landmark_covariances(self, slots: I64 | None = None) -> F64:
        """(k, 3, 3) marginal covariances of the landmarks in `slots` (None: all)."""
        L = self.n_landmarks
        slots = np.arange(L) if slots is None else np.asarray(slots, dtype=np.int64)
        idx = self.landmark_index(slots)
        return self.P[idx[:, :, None], idx[:, None, :]]

    def vehicle_x(self, name: str) -> F64:
        vb = self.vehicles[name]
        return self.x[vb.start : vb.start + vb.model.n]

    def vehicle_P(self, name: str) -> F64:
        vb = self.vehicles[name]
        s = slice(vb.start, vb.start + vb.model.n)
        return self.P[s, s]

    def predict(self, name: str, x_new: F64, F: F64, Q: F64) -> None:
        """Replace vehicle `name`'s block by x_new and propagate the covariance with its
        transition F and process noise Q (eq. 2 restricted to the vehicle block)."""
        vb = self.vehicles[name]
        s = slice(vb.start, vb.start + vb.model.n)
        self.x[s] = x_new
        rows = F @ self.P[s, :]  # F [P_vv P_vo]
        P_vv = rows[:, s] @ F.T + Q
        self.P[s, :] = rows
        self.P[:, s] = rows.T
        self.P[s, s] = 0.5 * (P_vv + P_vv.T)

    def add_landmarks(self, m: F64, P_mm: F64, P_mx: F64) -> I64:
        """Append k landmarks: positions m (k, 3), joint covariance P_mm (3k, 3k) and
        cross-covariance with the current state P_mx (3k, n). Returns their slots (k,)."""
        k = len(m)
        n = self.n
        self._reserve(n + 3 * k)
        self._x[n : n + 3 * k] = np.asarray(m, dtype=float).reshape(-1)
        self._P[n : n + 3 * k, :n] = P_mx
        self._P[:n, n : n + 3 * k] = P_mx.T
        self._P[n : n + 3 * k, n : n + 3 * k] = 0.5 * (P_mm + P_mm.T)
        self._n = n + 3 * k
        L = self.n_landmarks
        return np.arange(L - k, L)

    def remove_landmarks(self, slots: I64) -> I64:
        """Marginalise the landmarks in `slots` out. Returns the old slot of every remaining
        landmark in its new order (new slot i held old slot `kept[i]`)."""
        L = self.n_landmarks
        keep = np.ones(L, dtype=bool)
        keep[np.asarray(slots, dtype=np.int64)] = False
        kept = np.flatnonzero(keep)
        idx = np.concatenate([np.arange(self.n_vehicle_states), self.landmark_index(kept).ravel()])
        x, P = self.x[idx], self.P[np.ix_(idx, idx)]
        self._n = len(idx)
        self.x, self.P = x, P
        return kept

    def bounded_states(
        self, settings: FilterSettings, vehicles: Sequence[str] | None = None
    ) -> I64 | None:
        """State indices NH-infinity's bound is put on: None for bound "all", else the
        states of `vehicles` (None: every vehicle; possibly none)."""
        if settings.bound == "all":
            return None
        names = list(self.vehicles) if vehicles is None else list(vehicles)
        return np.concatenate(
            [self.vehicles[v].index for v in names] or [np.zeros(0, dtype=np.int64)]
        )

    def update(
        self,
        settings: FilterSettings,
        gamma: GammaPolicy,
        y: F64,
        h: F64,
        H: F64,
        cols: I64,
        R: F64,
        vehicles: Sequence[str] | None = None,
    ) -> UpdateResult:
        """One measurement update (`filters.update_inplace`) with H (m, len(cols)) touching
        state columns `cols`, in place on the state's storage (the result's x and P are the
        views `self.x`, `self.P`; they equal `filters.ekf_update` / `hinf_update` of the
        state before the update). NH-infinity with bound "vehicle": the bound is on the
        states of `vehicles` (None: every vehicle)."""
        return update_inplace(
            settings, gamma, self.x, self.P, y, h, H, cols, R,
            self.bounded_states(settings, vehicles), self._work_view(),
        )  # fmt: skip
