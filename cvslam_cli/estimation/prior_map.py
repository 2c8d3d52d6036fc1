"""Multi-session mapping: a `fuse` run that starts from a map saved by an earlier run
(`fuse.prior_map`, `cvslam fuse RUN --prior-map OTHER`; extension beyond the paper).

The prior map is a `LandmarkArchive` (`map.npz`: every landmark of the earlier run, with its
nav-frame mean, marginal covariance, descriptor and mean viewing direction). Its landmarks
are entered in the landmark book before the first frame (`PriorMap.seed`) as landmarks out of
the state, never observed in this session, and come into the filter only when a vehicle
sees them:

- a vehicle whose pose is known (in the map's nav frame: the config's or the logs' initial
  pose) finds them by predicted pixel and descriptor like the session's own evicted
  landmarks (`PriorLandmarks`, the re-activation step of `reactivation.py`: in view, inside
  the chi-square window of the vehicle's pose and the landmark's inflated marginal, ratio
  test, one consistent vehicle correction, at least `reactivation_min_landmarks`), and they
  are inserted conservatively. What the archive lost is more than for an eviction within a
  run: every prior landmark was correlated with the earlier session's trajectory, and so
  with the others: they share that session's error where they were mapped (a drift of the
  map's frame), which no inflation of independent marginals represents (n landmarks seen
  together would average it away as if independent; BENCHMARKS.md "Fuse: multi-session"
  measured the NEES of that). So the map's common error is a state of its own, the offset
  b (3 numbers, nav frame, m: prior position = true position + b + own error), started at
  0 with covariance B (`PriorMap.offset_covariance`: the largest common part the archived
  marginals allow, the per-axis minimum of their variances, inflated like them), added to
  the joint state as a static block (`OFFSET_BLOCK`, no motion, never bounded). A prior
  landmark enters as l = m_prior - b with its own error the archived marginal inflated by
  `prior_map_inflation`, or `refined_prior_map_inflation` for a map `cvslam refine` made
  (`prior_inflation`, `PriorLandmarks.reinsert`): correlated with b, and through b
  with every vehicle and landmark the map has touched, as the model says; the vehicles'
  updates with prior landmarks then estimate b (`run.yaml`: the offset found);
- a vehicle whose pose is unknown (`fuse.initial.unknown`) is localised in the state's and
  the prior map's landmarks (`unknown_pose.py`: PnP, the prior check, and against false
  localisation in a map of another place the same pose in `localise_confirm_frames`
  consecutive frames); the inlier prior landmarks are then inserted as above.

The run's map (`map.npz`, `map.csv`) holds the prior landmarks (updated where they were
observed again) and the new ones, each with its `session` (`merged_archive`): the prior's
sessions kept, the new landmarks one more than the prior's largest.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cvslam_cli.estimation.frame import FrameMatches
from cvslam_cli.estimation.landmark_coordinates import AnchoredInverseDepth
from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.reactivation import MAX_REACTIVATION_STD_M, Found, Reactivation
from cvslam_cli.estimation.settings import SlamSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehiclePose, VehicleRun
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.landmark_archive import LandmarkArchive

OFFSET_BLOCK = "prior map offset"
"""The joint state's block of the prior map's offset b (not a vehicle name: those are file
names, without spaces)."""


@dataclass(frozen=True)
class _Static:
    """The 'motion model' of the offset block: n states that never move (`JointState` needs
    only n; the block is never predicted)."""

    n: int = 3
    kind: str = "static"


def prior_inflation(settings: SlamSettings, archive: LandmarkArchive) -> F64:
    """(N,) the inflation of each prior landmark's marginal: `refined_prior_map_inflation`
    for one a batch solution estimated (`cvslam refine`: the exact marginal of one joint
    solution), else `prior_map_inflation` (a filter's, whose correlations were lost at every
    eviction). Chosen by NEES: BENCHMARKS.md "Fuse: multi-session (issue 20)"."""
    return np.where(
        archive.batch, settings.refined_prior_map_inflation, settings.prior_map_inflation
    )


class PriorMap:
    """The prior map of a run: `archive` (N landmarks), which become the book's ids 0..N-1
    (`seed`); `session` the number of this run's landmarks; `inflation` (N,) of each
    landmark's marginal (`prior_inflation`)."""

    def __init__(self, archive: LandmarkArchive, settings: SlamSettings) -> None:
        self.archive = archive
        self.n = len(archive)
        self.session = int(archive.session.max()) + 1 if self.n else 1
        self.inflation = prior_inflation(settings, archive)

    def offset_covariance(self) -> F64:
        """B (3, 3): the per-axis minimum of the archived landmarks' inflated variances (the
        common part of every landmark's error is no larger than any one's)."""
        var = self.inflation[:, None] * np.diagonal(self.archive.cov_nav_m2, axis1=1, axis2=2)
        var = var[np.all(np.isfinite(var), axis=1)]
        return np.diag(var.min(axis=0)) if len(var) else np.eye(3)

    def offset_block(self) -> tuple[str, Any, F64, F64]:
        """The offset b's block for `JointState` (module docstring): x0 = 0, P0 = B."""
        return OFFSET_BLOCK, _Static(), np.zeros(3), self.offset_covariance()

    def seed(self, book: LandmarkBook) -> None:
        """Enter the prior landmarks in the (empty) book, out of the state and observed by
        no vehicle of this session."""
        if book.count:
            raise ValueError("PriorMap.seed: the book must be empty")
        a = self.archive
        if not self.n:
            return
        ids = book.add(a.descriptor, 0, 0, a.true_id, a.view_dir_sum_nav)
        book.keep_slots(np.zeros(0, dtype=np.int64))  # none in the state
        book.observers[ids] = 0
        book.last_seen_ns[ids] = NEVER
        book.n_observations[ids] = a.n_observations
        book.first_seen_ns[ids] = a.first_seen_ns
        book.p_nav_m[ids] = a.p_nav_m
        book.cov_nav_m2[ids] = a.cov_nav_m2
        book.evicted_ns[ids] = a.evicted_ns
        book.reactivations[ids] = a.reactivations

    def count(self, book: LandmarkBook, slots: I64) -> int:
        """How many of the state's landmarks in `slots` came from the prior map."""
        return int(np.sum(book.slot_ids[np.asarray(slots, dtype=np.int64)] < self.n))

    def merged_archive(self, session: LandmarkArchive) -> LandmarkArchive:
        """The run's map: its book's archive `session` (the prior's landmarks first, as
        seeded) with the prior's vehicles' last observations and sessions restored, and
        the prior's batch estimates (`LandmarkArchive.batch`) still marked as such where
        this run did not observe them (an observed one is this filter's estimate now)."""
        a = self.archive
        vehicles = list(a.vehicles) + [v for v in session.vehicles if v not in a.vehicles]
        last = np.full((len(session), len(vehicles)), NEVER, dtype=np.int64)
        last[: self.n, : len(a.vehicles)] = a.last_seen_ns
        for j, v in enumerate(session.vehicles):
            col = vehicles.index(v)
            last[:, col] = np.maximum(last[:, col], session.last_seen_ns[:, j])
        sessions = np.full(len(session), self.session, dtype=np.int64)
        sessions[: self.n] = a.session
        batch = np.zeros(len(session), dtype=bool)
        batch[: self.n] = a.batch & np.all(session.last_seen_ns[: self.n] == NEVER, axis=1)
        fields = {k: getattr(session, k) for k in _ARCHIVE_FIELDS}
        return LandmarkArchive(
            **fields, vehicles=tuple(vehicles), last_seen_ns=last, session=sessions, batch=batch
        )


_ARCHIVE_FIELDS = (
    "landmark_id", "true_id", "p_nav_m", "cov_nav_m2", "descriptor", "view_dir_sum_nav",
    "first_seen_ns", "n_observations", "in_state", "evicted_ns", "reactivations", "coordinates",
)  # fmt: skip


class PriorLandmarks(Reactivation):
    """The prior map's landmarks not yet observed in this session, found in a frame and
    inserted like evicted ones (module docstring); once observed, an evicted prior landmark
    is the session's own (`Reactivation`)."""

    def __init__(
        self,
        state: JointState,
        book: LandmarkBook,
        settings: SlamSettings,
        R_pixel_hat: F64,
        prior: PriorMap,
    ) -> None:
        super().__init__(state, book, settings, R_pixel_hat)
        self.prior = prior

    @property
    def enabled(self) -> bool:
        return self.prior.n > 0

    def archived(self, t_ns: int) -> I64:
        """Ids of the prior landmarks out of the state, unobserved in this session, whose
        position is known to `MAX_REACTIVATION_STD_M`."""
        n, book = self.prior.n, self.book
        out = ~book.in_state_mask()[:n]
        unseen = np.all(book.last_seen_ns[:n] == NEVER, axis=1)
        known = book.known(np.arange(n), MAX_REACTIVATION_STD_M)
        return np.flatnonzero(out & unseen & known)

    def reinsert(self, run: VehicleRun, ids: I64) -> I64:
        """Put the prior landmarks `ids` into the state as l = m_prior - b, their own error
        the inflated archived marginal E (module docstring); returns their slots."""
        st, book = self.state, self.book
        b_rows = st.vehicles[OFFSET_BLOCK].index
        l_nav = book.p_nav_m[ids] - st.x[b_rows]
        E = self.inflated_cov(ids)
        if st.coords.anchored:
            slots = _anchored_on_offset(st, run, l_nav, E, b_rows)
        else:
            k = len(ids)
            P_ll = np.tile(st.P[np.ix_(b_rows, b_rows)], (k, k))
            for j in range(k):
                P_ll[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += E[j]
            slots = st.add_landmarks(l_nav, P_ll, -np.tile(st.P[b_rows, :], (k, 1)))
        book.readmit(ids)
        return slots

    def inflated_cov(self, ids: I64) -> F64:
        """(k, 3, 3) the prior landmarks' archived covariances, each inflated by its own
        `PriorMap.inflation`."""
        return self.prior.inflation[ids][:, None, None] * self.book.cov_nav_m2[ids]

    def find(self, run: VehicleRun, frame: FrameMatches, free: np.ndarray) -> Found:
        found = super().find(run, frame, free)
        # no absence to speak of: the landmarks come from another session
        return Found(found.ids, found.match_rows, np.zeros(len(found.ids), dtype=np.int64))


def _anchored_on_offset(st: JointState, run: VehicleRun, l_nav_m: F64, E: F64, b_rows: I64) -> I64:
    """Landmarks l = m - b (k, 3) with own errors E (k, 3, 3), written relative to a new
    clone a of run's vehicle pose: theta = f(l, a), so with G = [-T_m 1, T_a] on (b, a),
    P_tt = G P_(b,a) G^T + T_m E T_m^T and P_tx = G P_(b,a),x (as `reactivation._anchored`,
    with l correlated with the state through b)."""
    vin = run.vin
    pose = VehiclePose.of(st, vin)
    key, a_rows = pose.clone(st)
    R_cb, t_bc = vin.obs.R_cam_body[0], vin.obs.t_body_cam[0]
    theta, T_m, T_a = AnchoredInverseDepth().from_nav(l_nav_m, st.x[a_rows], R_cb, t_bc)
    k = len(l_nav_m)
    G = np.concatenate([-T_m.reshape(3 * k, 3), T_a.reshape(3 * k, 6)], axis=1)
    rows = np.concatenate([b_rows, a_rows])
    P_tx = G @ st.P[rows, :]
    P_tt = P_tx[:, rows] @ G.T
    own = T_m @ E @ np.swapaxes(T_m, 1, 2)
    for j in range(k):
        P_tt[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] += own[j]
    return st.add_landmarks(theta, 0.5 * (P_tt + P_tt.T), P_tx, key, R_cb, t_bc)
