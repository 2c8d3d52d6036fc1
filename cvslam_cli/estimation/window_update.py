"""The sliding-window update: every vehicle keeps clones of its last few poses in the state
and the feature tracks it follows without mapping them (`tracks.py`) correct those poses
(the MSCKF of Mourikis & Roumeliotis 2007, as OpenVINS's "MSCKF features" beside its SLAM
features).

Why: a landmark in the state costs O(n^2) per update and the state holds a few hundred, so
each frame is corrected by the few dozen landmarks it re-observes (on KITTI about 15 of some
230 stereo points: BENCHMARKS.md, "Fuse: consistency (issue 15)", third step). The other
points, followed over the window, still constrain the relative motion, at a cost linear in
their number and with no state of their own.

For a track with observations z_i (4,) from clones i = 1..L: its point f (nav) is the
Gauss-Newton least-squares fit of the stereo model (eq. 19) over the clones' poses; the
stacked residual r = z - h(x_c, f) ~ H_x dx_c + H_f df + noise. Projecting onto the left
null space of H_f (Q2^T, from a QR of H_f) removes the point's error: r0 = Q2^T r ~ H0 dx_c +
Q2^T noise, 4L - 3 rows whose noise is still sigma^2 I. A track whose r0 fails a chi-square
gate against H0 P_cc H0^T + R is dropped (a wrong match or a moving point). The tracks'
rows, stacked, are compressed by a QR when they outnumber the clones' states and applied
as one EKF / NH-infinity update on the clone columns; the vehicle states follow through
their correlation with the clones.

A clone is corrected by every frame while it is in the window (the tracks that end, and the
landmark updates through its correlation with the vehicle): when it is released (at the
first update after it left the window), its estimate is that frame's pose given the frames
after it, a fixed-lag smoother's (`LaggedPose`, written in place of the frame's own
estimate: `Slam._revise`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cvslam_cli.estimation.association import spread_order
from cvslam_cli.estimation.filters import FilterSettings, GammaPolicy
from cvslam_cli.estimation.frame import FrameMatches, WindowOutcome
from cvslam_cli.estimation.gauge import constrain
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.settings import WindowSettings
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.tracks import TrackBook, TrackObservations
from cvslam_cli.estimation.update import ExtraRows
from cvslam_cli.estimation.vehicle import VehicleInput, VehiclePose
from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True, eq=False)
class TrackResiduals:
    """Null-space residuals of the tracks that passed the gate: r (m,), H (m, 6 C) over the
    clones `clone_keys` (C,) in that order, how many tracks were used / gated out, and the
    sum of the used tracks' gate statistics r0^T S0^-1 r0 (`nis`) with their rows (`dof`)."""

    r: F64
    H: F64
    clone_keys: I64
    used: int
    rejected: int
    nis: float = float("nan")
    dof: int = 0


def fit_points(
    obs: StereoObservationModel, poses: F64, t: TrackObservations, clone_index: I64, iterations: int
) -> F64:
    """Gauss-Newton fit of each track's point f (T, 3) to its observations from the clone
    poses `poses` (C, 6) (p, Psi); clone_index (K,) each observation's row of `poses`."""
    f = t.m.copy()
    for _ in range(iterations):
        JtJ = np.zeros((t.n_tracks, 3, 3))
        Jtr = np.zeros((t.n_tracks, 3))
        for c in np.unique(clone_index):
            sel = np.flatnonzero(clone_index == c)
            z_hat, _, H_m = obs.predict(poses[c, :3], poses[c, 3:], f[t.track[sel]])
            r = t.z[sel] - z_hat
            np.add.at(JtJ, t.track[sel], np.swapaxes(H_m, 1, 2) @ H_m)
            np.add.at(Jtr, t.track[sel], np.einsum("kij,ki->kj", H_m, r))
        f = f + np.linalg.solve(JtJ + 1e-9 * np.eye(3), Jtr[..., None])[..., 0]
    return f


def track_residuals(
    obs: StereoObservationModel,
    state: JointState,
    t: TrackObservations,
    R_pixel_hat: F64,
    s: WindowSettings,
) -> TrackResiduals:
    """The gated null-space residuals of the tracks `t` (module docstring)."""
    keys, clone_index = np.unique(t.clone, return_inverse=True)
    rows = np.stack([state.anchor_rows(int(k)) for k in keys])  # (C, 6)
    poses = state.x[rows]
    f = fit_points(obs, poses, t, clone_index, s.iterations)
    K = len(t.z)
    r_all = np.empty((K, 4))
    H_pose = np.empty((K, 4, 6))
    H_f = np.empty((K, 4, 3))
    for c in range(len(keys)):
        sel = np.flatnonzero(clone_index == c)
        z_hat, H_pose[sel], H_f[sel] = obs.predict(poses[c, :3], poses[c, 3:], f[t.track[sel]])
        r_all[sel] = t.z[sel] - z_hat
    P_cc = state.P[np.ix_(rows.ravel(), rows.ravel())]
    sigma2 = float(R_pixel_hat[0, 0])
    C = len(keys)
    r_out: list[F64] = []
    H_out: list[F64] = []
    rejected = 0
    nis, dof = 0.0, 0
    # observations grouped by track (stable: each track's in time order), tracks by length
    order = np.argsort(t.track, kind="stable")
    lengths = np.bincount(t.track, minlength=t.n_tracks)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    for L in np.unique(lengths):
        tracks = np.flatnonzero(lengths == L)
        obs_rows = order[first[tracks][:, None] + np.arange(L)]  # (n, L)
        n = len(tracks)
        Hx = np.zeros((n, L, 4, C, 6))
        Hx[np.arange(n)[:, None], np.arange(L), :, clone_index[obs_rows], :] = H_pose[obs_rows]
        Hx = Hx.reshape(n, 4 * L, 6 * C)
        Q, _ = np.linalg.qr(H_f[obs_rows].reshape(n, 4 * L, 3), mode="complete")
        Q2t = np.swapaxes(Q[:, :, 3:], 1, 2)  # (n, 4L - 3, 4L)
        r0 = (Q2t @ r_all[obs_rows].reshape(n, 4 * L, 1))[..., 0]
        H0 = Q2t @ Hx
        S0 = H0 @ P_cc @ np.swapaxes(H0, 1, 2) + sigma2 * np.eye(4 * L - 3)
        d2 = np.einsum("ki,ki->k", r0, np.linalg.solve(S0, r0[..., None])[..., 0])
        ok = np.isfinite(d2) & (d2 <= s.gate_chi2[4 * L - 3])
        rejected += int(n - ok.sum())
        nis += float(d2[ok].sum())
        dof += int(ok.sum()) * (4 * L - 3)
        r_out.extend(r0[ok])
        H_out.extend(H0[ok])
    if not r_out:
        return TrackResiduals(np.zeros(0), np.zeros((0, 6 * len(keys))), keys, 0, rejected)
    r = np.concatenate(r_out)
    H = np.concatenate(H_out)
    if len(r) > H.shape[1]:  # QR compression: the same information in at most 6 C rows
        Q1, R1 = np.linalg.qr(H)
        r, H = Q1.T @ r, R1
    return TrackResiduals(r, H, keys, len(r_out), rejected, nis, dof)


@dataclass(frozen=True, eq=False)
class LaggedPose:
    """A frame's pose as the window last estimated it, when its clone is released (the frames
    after it have corrected it): the vehicle's name, the frame's stamp, pose (6,) (p_nav_m,
    euler_rad) and its covariance (6, 6)."""

    vehicle: str
    stamp_ns: int
    pose: F64
    cov: F64


@dataclass(eq=False)
class _VehicleWindow:
    clones: list[int] = field(default_factory=list)
    tracks: TrackBook = field(default_factory=TrackBook)


class SlidingWindow:
    """The clones and tracks of every vehicle, and their update, on the joint `state`.

    The rows of the tracks that end in a frame wait for the next update (of any vehicle) and
    are stacked into it (`pending_rows`, then `settle`), or applied alone when that frame has
    none (`flush`): one pass over the covariance per frame instead of two. The wait changes
    nothing the rows say: they touch only the clones, which no prediction moves, and a clone
    leaving the window is released only once its rows are applied.
    """

    def __init__(
        self,
        state: JointState,
        settings: WindowSettings,
        filter_settings: FilterSettings,
        gamma: GammaPolicy,
        R_pixel: F64,
    ) -> None:
        self.state = state
        self.settings = settings
        self.filter = filter_settings
        self.gamma = gamma
        self.R_pixel = R_pixel
        self.R_pixel_hat = filter_settings.measurement_noise(R_pixel)
        self._windows: dict[str, _VehicleWindow] = {}
        self._pending: list[TrackResiduals] = []
        self._leaving: list[int] = []
        self._frame_of: dict[int, tuple[str, int]] = {}  # clone key: (vehicle, stamp_ns)
        self._lagged: list[LaggedPose] = []

    def step(self, vin: VehicleInput, frame: FrameMatches, free: I64) -> WindowOutcome:
        """One frame of `vin`: clone its pose, continue or start tracks with the frame rows
        `free`, the rows of the tracks that end made pending, and the oldest clone let go
        (once they are applied)."""
        s = self.settings
        st = self.state
        w = self._windows.setdefault(vin.name, _VehicleWindow())
        pose = VehiclePose.of(st, vin)
        key, _ = pose.clone(st, pinned=True)
        w.clones.append(key)
        self._frame_of[key] = (vin.name, frame.stamp_ns)
        tracks = w.tracks
        cont, rows = tracks.match(
            vin, pose, frame, free, self.R_pixel, s.match_gate_chi2, s.descriptor_ratio,
            s.max_descriptor_distance,
        )  # fmt: skip
        m, cov = vin.obs.landmark_from_camera_point(
            pose.p_nav_m, pose.euler_rad, frame.p_cam_m[free], frame.cov_cam_m2[free], pose.cov
        )
        at = {r: i for i, r in enumerate(free.tolist())}
        idx = np.array([at[r] for r in rows.tolist()], dtype=np.int64)
        continued = np.zeros(len(tracks), dtype=bool)
        continued[cont] = True
        tracks.extend(cont, rows, key, frame, m[idx], cov[idx])
        # tracks end when lost, or when their first clone is about to leave the window
        leaving = w.clones[0] if len(w.clones) > s.window else None
        ended = ~continued | (tracks.first_clones() == leaving)
        res = self._residuals(vin, tracks.take(ended))
        new = np.ones(len(free), dtype=bool)
        new[idx] = False
        room = max(0, s.max_tracks - len(tracks))
        size = tuple(vin.features.rig.size_px[0])
        # spread over the image, never ranked by the measurement's own precision (that picks
        # the points whose noise shortened their depth: a biased window, NEES ~90 instead of
        # ~2 in the landmark-mode Monte Carlo; the same as new landmarks' priority)
        pick = np.flatnonzero(new)
        pick = pick[spread_order(frame.z[free[pick], :2], np.zeros(len(pick)), size)][:room]
        tracks.start(free[pick], key, frame, m[pick], cov[pick])
        if leaving is not None:
            w.clones.pop(0)
            self._leaving.append(leaving)
        return WindowOutcome(len(cont), *res)

    def _residuals(self, vin: VehicleInput, t: TrackObservations) -> tuple[int, int, float, int]:
        """The ended tracks' gated rows made pending; (used, rejected, gate NIS, its dof)."""
        if t.n_tracks == 0:
            return 0, 0, float("nan"), 0
        tr = track_residuals(vin.obs, self.state, t, self.R_pixel_hat, self.settings)
        if not len(tr.r):
            return 0, tr.rejected, float("nan"), 0
        self._pending.append(tr)
        return tr.used, tr.rejected, tr.nis, tr.dof

    def pending_rows(self) -> ExtraRows | None:
        """The pending rows as one block over the clones' present state columns (None if
        there are none), blind to the gauge when the state carries one."""
        if not self._pending:
            return None
        cols = [
            np.concatenate([self.state.anchor_rows(int(k)) for k in tr.clone_keys])
            for tr in self._pending
        ]
        H = np.zeros((sum(len(tr.r) for tr in self._pending), sum(len(c) for c in cols)))
        i = j = 0
        for tr, c in zip(self._pending, cols, strict=True):
            H[i : i + len(tr.r), j : j + len(c)] = tr.H
            i, j = i + len(tr.r), j + len(c)
        sigma2 = float(self.R_pixel[0, 0])
        r = np.concatenate([tr.r for tr in self._pending])
        cols = np.concatenate(cols)
        N = self.state.N
        if N is not None:  # the observability constraint (gauge.py)
            H = constrain(H, N[cols])
        return ExtraRows(r, H, cols, sigma2 * np.eye(len(r)))

    def settle(self) -> None:
        """The pending rows have been applied: forget them and release the clones that left,
        their poses kept as the window last estimated them (`take_lagged`)."""
        self._pending.clear()
        for key in self._leaving:
            self._lagged.append(self._lagged_pose(key, self._frame_of.pop(key)))
            self.state.release_anchor(key)
        self._leaving.clear()

    def take_lagged(self) -> list[LaggedPose]:
        """The poses of the clones released since the last call (`settle`)."""
        out, self._lagged = self._lagged, []
        return out

    def in_window(self) -> list[LaggedPose]:
        """The poses of the clones not released yet, those that left the window waiting for
        their rows too (as they are now: the run's end)."""
        keys = self._leaving + [k for w in self._windows.values() for k in w.clones]
        return [self._lagged_pose(k, self._frame_of[k]) for k in keys]

    def _lagged_pose(self, key: int, frame: tuple[str, int]) -> LaggedPose:
        rows = self.state.anchor_rows(key)
        assert rows is not None  # pinned until released
        vehicle, stamp_ns = frame
        return LaggedPose(
            vehicle, stamp_ns, self.state.x[rows].copy(), self.state.P[np.ix_(rows, rows)].copy()
        )

    def flush(self, bounded: Sequence[str]) -> None:
        """Apply the pending rows alone (a frame without a landmark update, the run's end)."""
        rows = self.pending_rows()
        if rows is not None:
            self.state.update(
                self.filter, self.gamma, rows.r, np.zeros(len(rows.r)), rows.H, rows.cols,
                rows.R, vehicles=bounded,
            )  # fmt: skip
        self.settle()
