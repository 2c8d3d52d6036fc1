"""The joint state of the central filter: every vehicle's block, then every landmark in the
state (paper eq. 3 and section "Cooperative VSLAM"):

    X = [X_v1 ... X_vM, landmarks ...],   P (n, n)

Vehicle blocks come first and keep their place; then, in the order they were added, each
landmark's own 3 numbers and, with anchored coordinates (`landmark_coordinates.py`), the
anchor clones (6 numbers: a vehicle pose, p and Psi) the landmarks refer to. A landmark's
columns (`landmark_columns`) are its anchor's and its own; outside the update everything
sees nav-frame positions and covariances (`landmarks`, `landmark_covariances`). The
structure the filter exploits:

- predict (eq. 1, 2) touches one vehicle block only: landmarks are static and the other
  vehicles unchanged, so with the vehicle's transition F and process noise Q over an interval
      P_vv <- F P_vv F^T + Q,    P_vo <- F P_vo    (o: every other state)
  costs O(n n_v), not O(n^3);
- an observation touches one vehicle and the landmarks it sees (H's non-zero columns), so the
  update costs O(n^2 m) (`filters.py`);
- adding a landmark appends 3 rows/columns (an anchor clone 6), removing landmarks deletes
  theirs, and an anchor's with its last landmark (Gaussian marginalisation).

x and P are views of storage with room to grow (capacity doubles when full). The
measurement update works on that storage in place (`filters.ekf_update_inplace`,
`filters.hinf_update_inplace`) with persistent work buffers of the same capacity, so an
update allocates no n x n array.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.estimation.filters import (
    BlockRows,
    FilterSettings,
    GammaPolicy,
    UpdateResult,
    update_inplace,
)
from cvslam_cli.estimation.gauge import has_down_translation, team_pivot, vehicle_basis
from cvslam_cli.estimation.landmark_coordinates import Cartesian, LandmarkCoordinates
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
    """Mean `x` (n,) and covariance `P` (n, n) of all vehicles and the landmarks in the state,
    written in the landmark `coords`."""

    def __init__(
        self,
        blocks: list[tuple[str, MotionModel, F64, F64]],
        coords: LandmarkCoordinates | None = None,
        gauge: bool = False,
    ) -> None:
        """blocks: (vehicle name, motion model, x0 (n_v,), P0 (n_v, n_v)) per vehicle;
        coords: how landmarks are written (default: Cartesian); gauge: carry the basis N of
        the unobservable directions and constrain the updates to them (`gauge.py`)."""
        self.coords = Cartesian() if coords is None else coords
        # per landmark slot: its own rows (L, 3), its anchor (L,) (-1: none), and its anchor
        # camera's R_cam_body (L, 3, 3) and t_body_cam (L, 3); per anchor: its rows (A, 6)
        self._own_rows = np.zeros((0, 3), dtype=np.int64)
        self._anchor_of = np.zeros(0, dtype=np.int64)
        self._R_cam_body = np.zeros((0, 3, 3))
        self._t_body_cam = np.zeros((0, 3))
        self._anchor_rows = np.zeros((0, 6), dtype=np.int64)
        self._anchor_key = np.zeros(0, dtype=np.int64)  # stable names of the anchors
        self._anchor_pinned = np.zeros(0, dtype=bool)  # kept even with no landmark on it
        self._next_anchor_key = 0
        # every landmark's nav position and Jacobian, kept while the landmarks' numbers and
        # layout are unchanged (`_nav_all`): visibility, association, re-activation and
        # eviction all read them, several times a frame
        self._layout = 0  # bumped whenever landmark slots are added or removed
        self._nav_cache: tuple[int, F64, F64, F64] | None = None
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
        # the gauge basis N (n, g) with the same room to grow (None: not carried)
        self._N: F64 | None = None
        if gauge:
            down = has_down_translation([b[1] for b in blocks])
            self._N = np.zeros((len(self._x), 4 if down else 3))
            self._pivot_ne_m = team_pivot([(b[1], np.asarray(b[2], dtype=float)) for b in blocks])
            for (_, model, x0, _), vb in zip(blocks, self.vehicles.values(), strict=True):
                self._N[vb.index] = vehicle_basis(
                    model, np.asarray(x0, dtype=float), down, self._pivot_ne_m
                )
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

    @property
    def N(self) -> F64 | None:
        """(n, g) the gauge basis (a view; `gauge.py`), None when it is not carried."""
        return None if self._N is None else self._N[: self._n]

    def gauge_rows(self, G: F64, rows: I64) -> F64 | None:
        """Gauge rows G N[rows] of new states y = G x[rows] + w (None: no gauge)."""
        return None if self._N is None else G @ self._N[rows]

    def landmark_gauge(self, slots: I64) -> F64 | None:
        """(k, 3, g) gauge rows of the landmarks' nav positions (None: no gauge)."""
        if self._N is None:
            return None
        slots = np.asarray(slots, dtype=np.int64)
        return self.landmarks_nav(slots)[1] @ self.N[self.landmark_columns(slots)]

    def reset_gauge(self, name: str) -> None:
        """Vehicle `name`'s gauge rows from the symmetry at its state now (its pose was set
        anew, e.g. by localisation in the map)."""
        if self._N is not None:
            vb = self.vehicles[name]
            down = self._N.shape[1] == 4
            self._N[vb.index] = vehicle_basis(vb.model, self.x[vb.index], down, self._pivot_ne_m)

    def forget(self, name: str, rows: I64, variances: F64) -> None:
        """Vehicle `name`'s block made independent of the rest of the state, and its states
        `rows` (indices into the block) independent of its others with `variances` (k,):
        what is left when the vehicle's estimate of those states is known to be wrong
        (`relocalisation.py`). Its gauge rows are set anew from its state (`reset_gauge`)."""
        vb = self.vehicles[name]
        s = slice(vb.start, vb.start + vb.model.n)
        P_vv = self.P[s, s].copy()
        self.P[s, :] = 0.0
        self.P[:, s] = 0.0
        rows = np.asarray(rows, dtype=np.int64)
        P_vv[rows, :] = 0.0
        P_vv[:, rows] = 0.0
        P_vv[rows, rows] = variances
        self.P[s, s] = P_vv
        self.reset_gauge(name)

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
        if self._N is not None:
            N = np.zeros((new_cap, self._N.shape[1]))
            N[: self._n] = self._N[: self._n]
            self._N = N
        self._work = np.empty(2 * new_cap**2)

    def _work_view(self) -> F64:
        n = self._n
        return self._work[: 2 * n * n].reshape(2, n, n)

    @property
    def n(self) -> int:
        return self._n

    @property
    def n_landmarks(self) -> int:
        return len(self._own_rows)

    @property
    def n_anchors(self) -> int:
        return len(self._anchor_rows)

    def _slots(self, slots: I64 | None) -> I64:
        return np.arange(self.n_landmarks) if slots is None else np.asarray(slots, np.int64)

    def landmark_index(self, slots: I64) -> I64:
        """Own state rows of the landmarks in `slots` (k,) -> (k, 3)."""
        return self._own_rows[np.asarray(slots, dtype=np.int64)]

    def landmark_columns(self, slots: I64) -> I64:
        """State rows a landmark's position depends on, (k, coords.size): its anchor's (if
        any), then its own."""
        slots = np.asarray(slots, dtype=np.int64)
        own = self._own_rows[slots]
        if not self.coords.anchored:
            return own
        return np.concatenate([self._anchor_rows[self._anchor_of[slots]], own], axis=1)

    def landmarks_nav(self, slots: I64 | None = None) -> tuple[F64, F64]:
        """Nav-frame positions (k, 3) of the landmarks in `slots` (None: all) and their
        Jacobians w.r.t. their columns (k, 3, coords.size) (new arrays)."""
        m, M = self._nav_all()
        if slots is None:
            return m.copy(), M.copy()
        slots = np.asarray(slots, dtype=np.int64)
        return m[slots], M[slots]

    def _nav_all(self) -> tuple[F64, F64]:
        """Every landmark's `coords.to_nav`, computed once for as long as the landmarks'
        numbers in x and their layout stay the same (x is a public view, so the numbers
        themselves are compared: O(L size), against the conversion's trigonometry).
        `to_nav` works row by row, so a row is the same whether converted alone or with
        all (bit for bit)."""
        params = self.x[self.landmark_columns(np.arange(self.n_landmarks))]
        c = self._nav_cache
        if c is not None and c[0] == self._layout and np.array_equal(c[1], params):
            return c[2], c[3]
        m, M = self.coords.to_nav(params, self._R_cam_body, self._t_body_cam)
        m, M = np.ascontiguousarray(m), np.ascontiguousarray(M)
        self._nav_cache = (self._layout, params, m, M)
        return m, M

    def landmarks(self, slots: I64 | None = None) -> F64:
        """(k, 3) nav-frame positions of the landmarks in `slots` (None: all)."""
        return self.landmarks_nav(slots)[0]

    def landmark_covariances(self, slots: I64 | None = None) -> F64:
        """(k, 3, 3) nav-frame marginal covariances of the landmarks in `slots` (None: all)."""
        slots = self._slots(slots)
        cols = self.landmark_columns(slots)
        P_cc = self.P[cols[:, :, None], cols[:, None, :]]
        if not self.coords.anchored:
            return P_cc
        M = self.landmarks_nav(slots)[1]
        return M @ P_cc @ np.swapaxes(M, 1, 2)

    def vehicle_rows(self, bits: int) -> I64:
        """State rows of the vehicles whose bits are set in `bits` (bit i: the i-th vehicle,
        the landmark book's numbering), in the state's order."""
        blocks = [vb.index for i, vb in enumerate(self.vehicles.values()) if bits >> i & 1]
        return np.concatenate(blocks) if blocks else np.zeros(0, dtype=np.int64)

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
        if self._N is not None:
            self._N[s] = F @ self._N[s]

    def _append(self, x_new: F64, P_new: F64, P_cross: F64, N_new: F64 | None) -> I64:
        """Append r states: mean x_new (r,), covariance P_new (r, r), cross-covariance with
        the current state P_cross (r, n), gauge rows N_new (r, g) (required when the gauge
        is carried). Returns their rows (r,)."""
        r = len(x_new)
        n = self.n
        self._reserve(n + r)
        if self._N is not None:
            if N_new is None:
                raise ValueError("JointState: new states need their gauge rows")
            self._N[n : n + r] = N_new
        self._x[n : n + r] = x_new
        self._P[n : n + r, :n] = P_cross
        self._P[:n, n : n + r] = P_cross.T
        self._P[n : n + r, n : n + r] = 0.5 * (P_new + P_new.T)
        self._n = n + r
        return np.arange(n, n + r)

    def add_anchor(
        self, x_a: F64, P_aa: F64, P_ax: F64, pinned: bool = False, *, N_a: F64 | None = None
    ) -> tuple[int, I64]:
        """Append an anchor clone: a pose (p, Psi) x_a (6,), its covariance P_aa (6, 6),
        cross-covariance with the current state P_ax (6, n) and gauge rows N_a (6, g) (None
        without a gauge; `gauge_rows`). Returns its key (a name that
        stays valid while the anchor is in the state; `anchor_rows`) and its rows (6,). An
        unpinned anchor leaves with its last landmark; a pinned one (a clone of the track
        window, `tracks.py`) stays until `release_anchor`."""
        key = self._next_anchor_key
        self._next_anchor_key += 1
        rows = self._append(np.asarray(x_a, dtype=float), P_aa, P_ax, N_a)
        self._anchor_rows = np.concatenate([self._anchor_rows, rows[None]])
        self._anchor_key = np.concatenate([self._anchor_key, [key]])
        self._anchor_pinned = np.concatenate([self._anchor_pinned, [pinned]])
        return key, rows

    def release_anchor(self, key: int) -> None:
        """Unpin the anchor `key`: marginalised now unless a landmark still refers to it."""
        index = self._anchor_index(key)
        if index is not None:
            self._anchor_pinned[index] = False
            self.remove_landmarks(np.zeros(0, dtype=np.int64))

    def _anchor_index(self, key: int) -> int | None:
        hit = np.flatnonzero(self._anchor_key == key)
        return int(hit[0]) if len(hit) else None

    def anchor_rows(self, key: int) -> I64 | None:
        """State rows (6,) of the anchor `key`; None once it has left the state."""
        index = self._anchor_index(key)
        return None if index is None else self._anchor_rows[index]

    def add_landmarks(
        self,
        params: F64,
        P_pp: F64,
        P_px: F64,
        anchor_key: int | None = None,
        R_cam_body: F64 | None = None,
        t_body_cam: F64 | None = None,
        *,
        N_p: F64 | None = None,
    ) -> I64:
        """Append k landmarks: their own numbers params (k, 3) (Cartesian: m; anchored:
        theta), joint covariance P_pp (3k, 3k), cross-covariance with the current state
        P_px (3k, n); anchored coordinates: the anchor they refer to (its key) and its
        camera's R_cam_body (3, 3) and t_body_cam (3,); gauge rows N_p (3k, g) (required
        when the state carries a gauge; `gauge_rows`). Returns their slots (k,)."""
        k = len(params)
        index = None if anchor_key is None else self._anchor_index(anchor_key)
        anchor = -1 if index is None else index
        rows = self._append(np.asarray(params, dtype=float).reshape(-1), P_pp, P_px, N_p)
        R = np.eye(3) if R_cam_body is None else np.asarray(R_cam_body, dtype=float)
        t = np.zeros(3) if t_body_cam is None else np.asarray(t_body_cam, dtype=float)
        self._own_rows = np.concatenate([self._own_rows, rows.reshape(k, 3)])
        self._anchor_of = np.concatenate([self._anchor_of, np.full(k, anchor, dtype=np.int64)])
        self._R_cam_body = np.concatenate([self._R_cam_body, np.broadcast_to(R, (k, 3, 3))])
        self._t_body_cam = np.concatenate([self._t_body_cam, np.broadcast_to(t, (k, 3))])
        self._layout += 1
        L = self.n_landmarks
        return np.arange(L - k, L)

    def remove_landmarks(self, slots: I64) -> I64:
        """Marginalise the landmarks in `slots` out, and the anchors no remaining landmark
        refers to. Returns the old slot of every remaining landmark in its new order (new
        slot i held old slot `kept[i]`)."""
        keep = np.ones(self.n_landmarks, dtype=bool)
        keep[np.asarray(slots, dtype=np.int64)] = False
        kept = np.flatnonzero(keep)
        used = self._anchor_pinned.copy()
        used[self._anchor_of[kept][self._anchor_of[kept] >= 0]] = True
        keep_rows = np.ones(self.n, dtype=bool)
        keep_rows[self._own_rows[~keep].ravel()] = False
        keep_rows[self._anchor_rows[~used].ravel()] = False
        if keep_rows.all():  # nothing leaves: the layout stays
            return kept
        idx = np.flatnonzero(keep_rows)
        new_row = np.cumsum(keep_rows) - 1  # old row -> new row, for the rows kept
        new_anchor = np.cumsum(used) - 1
        _compact(self._P, self._x, keep_rows)
        if self._N is not None:
            self._N[: len(idx)] = self._N[idx]
        self._n = len(idx)
        anchor_of = self._anchor_of[kept]
        has = anchor_of >= 0
        anchor_of[has] = new_anchor[anchor_of[has]]
        self._anchor_of = anchor_of
        self._own_rows = new_row[self._own_rows[kept]]
        self._anchor_rows = new_row[self._anchor_rows[used]]
        self._anchor_key = self._anchor_key[used]
        self._anchor_pinned = self._anchor_pinned[used]
        self._R_cam_body, self._t_body_cam = self._R_cam_body[kept], self._t_body_cam[kept]
        self._layout += 1
        return kept

    def anchor_loads(self) -> I64:
        """(n_anchors,) how many landmarks refer to each anchor."""
        used = self._anchor_of[self._anchor_of >= 0]
        return np.bincount(used, minlength=self.n_anchors).astype(np.int64)

    def anchors_of(self, slots: I64) -> I64:
        """(k,) keys of the anchors the anchored landmarks `slots` refer to."""
        return self._anchor_key[self._anchor_of[np.asarray(slots, dtype=np.int64)]]

    def anchor_keys(self) -> I64:
        """(n_anchors,) every anchor's key, in state order."""
        return self._anchor_key.copy()

    def anchor_pinned(self) -> np.ndarray:
        """(n_anchors,) bool: which anchors are pinned (`add_anchor`), in state order."""
        return self._anchor_pinned.copy()

    def reanchor(
        self, slots: I64, key: int, theta: F64, J_old: F64, J_new: F64, R_cam_body: F64,
        t_body_cam: F64,
    ) -> None:  # fmt: skip
        """Write the anchored landmarks `slots` (k,) relative to the anchor `key` (whose left
        camera is R_cam_body (3, 3), t_body_cam (3,)): their new numbers theta (k, 3), with
        d theta / d (their columns, `landmark_columns`) J_old (k, 3, 9) and d theta / d (the
        new anchor's rows) J_new (k, 3, 6), evaluated at the estimate. A change of
        coordinates: x and P <- T x, T P T^T with T the identity but for the landmarks' own
        rows (and the gauge's rows likewise). Anchors left without a landmark (and not
        pinned) leave the state."""
        slots = np.asarray(slots, dtype=np.int64)
        k = len(slots)
        a_rows = self.anchor_rows(key)
        if a_rows is None:
            raise ValueError(f"JointState: anchor {key} is not in the state")
        own = self._own_rows[slots].ravel()
        columns = self.landmark_columns(slots)  # (k, 9)
        src = np.unique(np.concatenate([columns.ravel(), a_rows]))
        where = np.searchsorted(src, columns)  # -> src columns
        A = np.zeros((3 * k, len(src)))
        a_at = np.searchsorted(src, a_rows)
        for j in range(k):
            A[3 * j : 3 * j + 3, where[j]] += J_old[j]
            A[3 * j : 3 * j + 3, a_at] += J_new[j]
        P = self.P
        AP = A @ P[src, :]  # (3k, n): the new rows
        block = AP[:, src] @ A.T
        P[own, :] = AP
        P[:, own] = AP.T
        P[np.ix_(own, own)] = 0.5 * (block + block.T)
        if self._N is not None:
            self._N[own] = A @ self._N[src]
        self._x[own] = np.asarray(theta, dtype=float).ravel()
        self._anchor_of[slots] = self._anchor_index(key)
        self._R_cam_body[slots] = R_cam_body
        self._t_body_cam[slots] = t_body_cam
        self._layout += 1
        self.remove_landmarks(np.zeros(0, dtype=np.int64))

    def bounded_states(
        self,
        settings: FilterSettings,
        vehicles: Sequence[str] | None = None,
        cols: I64 | None = None,
    ) -> I64 | None:
        """State indices NH-infinity's bound is put on: None for bound "all", else the
        states of `vehicles` (None: every vehicle; possibly none); bound "observer": of
        those, only the vehicles whose states the update's columns `cols` touch (the
        observing vehicle: l = 15 bounded states instead of 15 per vehicle)."""
        if settings.bound == "all":
            return None
        names = list(self.vehicles) if vehicles is None else list(vehicles)
        if settings.bound == "observer" and cols is not None:
            touched = np.zeros(self.n_vehicle_states, dtype=bool)
            touched[cols[cols < self.n_vehicle_states]] = True
            names = [v for v in names if touched[self.vehicles[v].index].any()]
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
        blocks: BlockRows | None = None,
    ) -> UpdateResult:
        """One measurement update (`filters.update_inplace`) with H (m, len(cols)) touching
        state columns `cols`, in place on the state's storage (the result's x and P are the
        views `self.x`, `self.P`; they equal `filters.ekf_update` / `hinf_update` of the
        state before the update). NH-infinity with bound "vehicle": the bound is on the
        states of `vehicles` (None: every vehicle); "observer": on those of them that H
        touches (`bounded_states`). `blocks`: H's known zeros (`filters.BlockRows`)."""
        return update_inplace(
            settings, gamma, self.x, self.P, y, h, H, cols, R,
            self.bounded_states(settings, vehicles, cols), self._work_view(), blocks,
        )  # fmt: skip


def _compact(P: F64, x: F64, keep: np.ndarray) -> None:
    """The kept states moved to the front of their storage, in place: x[:k] = x[keep] and
    P[:k, :k] = P[keep][:, keep] (k kept of n = len(keep)), by the blocks that runs of kept
    rows and columns make. Copied in row-major order of the blocks, each one's destination
    up and left of its source, no block overwrites one not yet read (a block overlapping its
    own source is buffered by numpy); the same numbers as the gather, which a state missing
    a few scattered rows would build from n^2 single reads and then copy back."""
    edges = np.diff(np.concatenate([[0], keep.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()
    to = np.cumsum([0] + [e - s for s, e in zip(starts, ends, strict=True)]).tolist()
    runs = list(zip(starts, ends, to[:-1], strict=True))  # (first, end, new first)
    for s0, e0, i0 in runs:
        x[i0 : i0 + e0 - s0] = x[s0:e0]
        for s1, e1, j0 in runs:
            P[i0 : i0 + e0 - s0, j0 : j0 + e1 - s1] = P[s0:e0, s1:e1]
