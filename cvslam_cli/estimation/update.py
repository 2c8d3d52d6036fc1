"""The visual measurement update: stereo observations of landmarks (eq. 19) stacked into one
EKF or NH-infinity update of the joint state (`filters.py`).

Each observation z_j = (u_l, v_l, u_r, v_r) of landmark j gives 4 rows of H, touching the
observing vehicle's block (H_v,j) and landmark j's columns (H_m,j: its 3, and its anchor's
with anchored coordinates) only; the noise is the pixel noise, independent per coordinate
(R = sigma_px^2 I; an observation of another vehicle's landmark may have its own,
`association.noise_scale`), scaled by the filter (eq. 14). With a rectified rig the two v
rows are one (`observation.mean_v_rows`): 3 rows per observation, (u_l, (v_l + v_r) / 2, u_r) with
noise sigma_px^2 diag(1, 1/2, 1), the same update to rounding at three quarters of the
rows. The NIS keeps every coordinate's term: the difference (v_l - v_r), which says nothing
about the state, adds its own (innovation variance 2 sigma_hat^2), so NIS and its degrees of
freedom (4 per observation) mean what they meant with four rows. An observation's bearing
noise may be scaled by its keypoint's octave (`octave_noise.py`): its noise is then sigma_px^2
(I + (b - 1) BEARING_ROWS) (`observation.BEARING_ROWS`: the bearing's part, common to both
images), the bearing's variance b times the filter's and the disparity's and the v
difference's as they were. Rows of another kind (the sliding window's, `window_update.py`)
may be stacked into the same update: one pass over the covariance instead of two.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from cvslam_cli.estimation.association import (
    LandmarkErrors,
    LandmarkPrediction,
    predict_in_state,
)
from cvslam_cli.estimation.filters import BlockRows, FilterSettings, GammaPolicy, UpdateResult
from cvslam_cli.estimation.gauge import constrain
from cvslam_cli.estimation.observation import BEARING_ROWS, MEAN_V_ROWS, mean_v_rows
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehicleInput, VehiclePose
from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True, eq=False)
class ExtraRows:
    """Linear rows stacked into an update: innovation r (m,) ~ H (m, c) dx[cols] + noise of
    covariance R (m, m) (unscaled: the filter scales it as the pixels'), cols (c,) state
    columns."""

    r: F64
    H: F64
    cols: I64
    R: F64


@dataclass(frozen=True, eq=False)
class _Stacked:
    """An update's stacked rows: H (m, c) over the state columns `cols` (c,), noise R (m, m)
    (unscaled), measurement y and prediction h (m,), H's known zeros `blocks`, and the NIS
    term of the v differences the rows leave out."""

    H: F64
    cols: I64
    R: F64
    y: F64
    h: F64
    blocks: BlockRows
    nis_v_difference: float


def _gain_step(P: F64, s: _Stacked, R_hat: F64) -> F64:
    """K (y - h) (n,) for the stacked rows `s`, K = P H^T (H P H^T + R_hat)^-1 (repeated
    columns add up, as in the update)."""
    PHt = P[s.cols].T @ s.H.T  # (n, m): P[cols].T reads P's rows (P is symmetric)
    S = s.H @ PHt[s.cols] + R_hat
    return PHt @ np.linalg.solve(0.5 * (S + S.T), s.y - s.h)


class VisualUpdater:
    """Predictions and stacked updates on `state` with the filter `settings`, the pixel
    noise `pixel_sigma_px` and the run's gamma policy. `R_pixel` (4, 4): the noise of one
    stereo observation; `R_pixel_hat`: as the filter scales it (eq. 14); `R_mean_v` (3, 3):
    the noise of a rectified rig's three rows (module docstring)."""

    def __init__(self, state: JointState, settings: FilterSettings, pixel_sigma_px: float) -> None:
        self.state = state
        self.settings = settings
        self.R_pixel = np.eye(4) * pixel_sigma_px**2
        self.R_pixel_hat = settings.measurement_noise(self.R_pixel)
        self.R_mean_v = MEAN_V_ROWS @ self.R_pixel @ MEAN_V_ROWS.T
        # the part of R that is the bearing's, common to both images (module docstring)
        self.W_pixel = pixel_sigma_px**2 * BEARING_ROWS
        self.W_mean_v = MEAN_V_ROWS @ self.W_pixel @ MEAN_V_ROWS.T
        # innovation variance of v_l - v_r, which no state moves
        self._var_v_difference = float(self.R_pixel_hat[1, 1] + self.R_pixel_hat[3, 3])
        self.gamma = GammaPolicy(settings)

    def predict(
        self, pose: VehiclePose, slots: I64, noise_scale: F64 | None = None
    ) -> tuple[LandmarkPrediction, LandmarkErrors]:
        """The landmarks in `slots` predicted into the images of the vehicle at `pose` (the
        state's now) with their innovation covariances (with R_hat, times `noise_scale` (k,) per
        landmark when given: `association.noise_scale`); also their covariance blocks with the
        vehicle (`association.LandmarkErrors`)."""
        return predict_in_state(self.state, pose, slots, self.R_pixel_hat, noise_scale)

    def update(
        self,
        v_idx: I64,
        pred: LandmarkPrediction,
        rows: I64,
        z: F64,
        bounded: Sequence[str],
        extra: ExtraRows | None = None,
        bearing_scale: F64 | None = None,
    ) -> UpdateResult:
        """One update (eq. 19) with observations z (k, 4) of the predicted landmarks `pred`
        rows `rows` (k,) by the vehicle whose state rows are v_idx, and the `extra` rows if
        any; NH-infinity's bound on the vehicles `bounded`; `bearing_scale` (k,): each
        observation's bearing noise variance over the filter's (module docstring; None: 1)."""
        return self._apply(self._stack(v_idx, pred, rows, z, extra, bearing_scale), bounded)

    def iterated_update(
        self,
        vin: VehicleInput,
        pred: LandmarkPrediction,
        rows: I64,
        z: F64,
        bounded: Sequence[str],
        extra: ExtraRows | None = None,
        iterations: int = 5,
        bearing_scale: F64 | None = None,
    ) -> tuple[UpdateResult, int]:
        """`update` relinearised at its own estimate (the iterated EKF: Gauss-Newton on the
        update's cost, for a correction too large for one linearisation): with x0 the state
        before, x_(i+1) = x0 + K_i (y - h(x_i) - H_i (x0 - x_i)), K_i the gain at x_i (the
        same for NH-infinity, eq. 14's R_hat), the landmarks `rows` of `pred` predicted
        again from vin's pose at each x_i, at most `iterations` linearisations, until a
        step moves no state by more than 1e-6 of its units or a step is larger than the
        one before (not converging: the estimate before it is kept, from the linearisation
        that gave it); the state is back at x0 for the update itself; the covariance (and
        NH-infinity's bound) then from the last one, as `update` does; also how many
        linearisations it took."""
        st = self.state
        v_idx = st.vehicles[vin.name].index
        slots = pred.slots[rows]
        scale = None if pred.noise_scale is None else pred.noise_scale[rows]
        x0 = st.x.copy()
        stacked = self._stack(v_idx, pred, rows, z, extra, bearing_scale, x0)  # at x0
        previous = stacked
        done, last_step = 1, np.inf
        try:
            for _ in range(iterations - 1):
                x_next = x0 + _gain_step(st.P, stacked, self.settings.measurement_noise(stacked.R))
                step = float(np.max(np.abs(x_next - st.x)))
                if step > last_step:  # not converging: back to the linearisation that gave x
                    stacked, done = previous, done - 1
                    break
                st.x, last_step = x_next, step
                pred, _ = self.predict(VehiclePose.of(st, vin), slots, scale)
                previous = stacked
                stacked = self._stack(
                    v_idx, pred, np.arange(len(slots)), z, extra, bearing_scale, x0
                )
                done += 1
                if step < 1e-6:
                    break
        finally:
            st.x = x0
        return self._apply(stacked, bounded), done

    def _stack(
        self,
        v_idx: I64,
        pred: LandmarkPrediction,
        rows: I64,
        z: F64,
        extra: ExtraRows | None,
        bearing_scale: F64 | None = None,
        x0: F64 | None = None,
    ) -> _Stacked:
        """The stacked rows of an update (module docstring); with `x0`, linearised at the
        state now for an estimate relative to x0 (`iterated_update`: h + H (x0 - x))."""
        k, nv = len(rows), len(v_idx)
        lm_cols = self.state.landmark_columns(pred.slots[rows])  # (k, d)
        d = lm_cols.shape[1]
        z_obs, h_obs, H_v, H_m = z, pred.z[rows], pred.H_v[rows], pred.H_m[rows]
        if self.state.N is not None:  # observability constraint, one observation at a time
            H_v, H_m = self._constrained(v_idx, lm_cols, H_v, H_m)
        R_obs, W_obs, nis_v_difference = self.R_pixel, self.W_pixel, 0.0
        scale = None if pred.noise_scale is None else pred.noise_scale[rows]
        if pred.rectified:  # 3 rows per observation (module docstring)
            e = (z_obs[:, 1] - h_obs[:, 1]) - (z_obs[:, 3] - h_obs[:, 3])
            e_w = e if scale is None else e / scale
            nis_v_difference = float(e @ e_w) / self._var_v_difference
            z_obs, h_obs, H_v, H_m = (mean_v_rows(a) for a in (z_obs, h_obs, H_v, H_m))
            R_obs, W_obs = self.R_mean_v, self.W_mean_v
        r = len(R_obs)  # rows per observation
        H_lm = np.zeros((k, r, k, d))  # landmark j's rows touch only its columns
        H_lm[np.arange(k), :, np.arange(k), :] = H_m
        H = np.concatenate([H_v.reshape(r * k, nv), H_lm.reshape(r * k, d * k)], axis=1)
        # an anchor shared by several landmarks appears once per landmark: the update is
        # linear in H's columns, so repeated state columns add up
        cols = np.concatenate([v_idx, lm_cols.reshape(-1)])
        # observation j's noise block: scale_j (R_obs + (b_j - 1) W_obs) (`association.
        # noise_scale`; b_j its bearing's, module docstring), block-diagonal
        R_j = np.broadcast_to(R_obs, (k, r, r))
        if bearing_scale is not None:
            R_j = R_j + (np.asarray(bearing_scale) - 1.0)[:, None, None] * W_obs
        if scale is not None:
            R_j = R_j * scale[:, None, None]
        R_full = np.zeros((k, r, k, r))
        R_full[np.arange(k), :, np.arange(k), :] = R_j
        R = R_full.reshape(r * k, r * k)
        y, h = z_obs.reshape(-1), h_obs.reshape(-1)
        if x0 is not None:
            h = h + H @ (x0 - self.state.x)[cols]
        tail = 0
        if extra is not None:  # block-diagonal: the two kinds of rows touch their own columns
            m, tail = extra.H.shape
            H = np.block([[H, np.zeros((len(H), tail))], [np.zeros((m, H.shape[1])), extra.H]])
            cols = np.concatenate([cols, extra.cols])
            R = np.block([[R, np.zeros((len(R), m))], [np.zeros((m, len(R))), extra.R]])
            # linear rows about x0: h(x) + H (x0 - x) = 0 at any x
            y, h = np.concatenate([y, extra.r]), np.concatenate([h, np.zeros(m)])
        return _Stacked(H, cols, R, y, h, BlockRows(nv, r, d, tail), nis_v_difference)

    def _apply(self, s: _Stacked, bounded: Sequence[str]) -> UpdateResult:
        """The update of the state with stacked rows `s`; P H^T from H's non-zero blocks
        only (the vehicle's columns, then r x d per landmark, then the extra rows' own)."""
        res = self.state.update(
            self.settings, self.gamma, s.y, s.h, s.H, s.cols, s.R, vehicles=bounded,
            blocks=s.blocks,
        )  # fmt: skip
        return replace(res, nis=res.nis + s.nis_v_difference)

    def _constrained(self, v_idx: I64, lm_cols: I64, H_v: F64, H_m: F64) -> tuple[F64, F64]:
        """H_v (k, r, n_v) and H_m (k, r, d) of k observations, each modified over its own
        columns (the vehicle's and its landmark's) so that it sees nothing of the gauge
        (`gauge.constrain`)."""
        N = self.state.N
        assert N is not None
        k, nv = len(lm_cols), len(v_idx)
        N_j = np.concatenate([np.broadcast_to(N[v_idx], (k, nv, N.shape[1])), N[lm_cols]], axis=1)
        H_j = constrain(np.concatenate([H_v, H_m], axis=2), N_j)
        return H_j[:, :, :nv], H_j[:, :, nv:]
