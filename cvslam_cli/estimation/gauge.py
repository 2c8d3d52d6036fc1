"""The gauge of the joint state and the observability-constrained update (extension beyond
the paper: Huang, Mourikis and Roumeliotis 2010, "Observability-based rules for designing
consistent EKF SLAM estimators"; Hesch et al. 2014 for visual-inertial navigation).

No measurement of the filter sees where the whole team is or which way it faces: moving
every vehicle and every landmark by a translation t and turning them all by an angle about
the nav frame's down axis leaves every image, every IMU sample and every odometry reading as
it was. In the linearised filter these are the columns of a basis N (n, g) of the joint
state, which the measurements must never learn about: H N = 0. The exact system has this
property; the EKF does not, because it evaluates each Jacobian at a different estimate (the
transition at the updated state, each update at the state of its time), so the directions
the updates leave alone drift from the ones propagation carried, and every frame adds a
little information along them. Re-activation adds much more: an evicted landmark put back
with its archived marginal and no correlation reads as an absolute reference, and many of
them add up (on `uav2_paper` seed 5, 100x the translation information the initial prior
gave). It shows as a position standard deviation flat over a 145 m drive (BENCHMARKS.md,
"Fuse: consistency (issue 15)", ninth step): the covariance claims an absolute position the
sensors never gave, and the position NEES grows with the distance travelled. (The heading
is not in this list by itself: two vehicles whose initial positions are known to 0.1 m and
lie 75 m apart do fix the team's heading to a few mrad once they share landmarks.)

The cure kept here (`fuse.observability_constrained`): the state carries N (`JointState`),
- started at each vehicle's initial state from the symmetry (`vehicle_basis`): the
  position rows move with t, the nav-frame position and velocity rows turn with the yaw
  angle (d(Rz p)/d angle = (-p_e, p_n, 0) for a turn about the origin), the yaw row moves
  with it, body-frame states and biases do not move. The turn is taken about the team's
  start (`team_pivot`), not the nav frame's origin: the same directions, with N's numbers
  on the scale of the team's ground wherever the origin lies (thousands of kilometres away
  in a georeferenced frame, a turn about it swamps a point's covariance put back,
  `gauge_correlated`, in rounding);
- propagated with the vehicle's transition, N_v <- F N_v (`JointState.predict`);
- extended by the chain rule for every state added: a new state y = G x_rows + w has rows
  G N[rows] (a clone copies its vehicle's rows; an anchored inverse depth relative to a clone
  of the pose it was measured from has zero rows);
- kept for the landmarks that leave the state (their nav rows, in the landmark book), and
  given back to them when re-activation puts them back, with a cross-covariance with the
  gauge error the states of their group of vehicles read (`gauge_correlated`), so that they
  add no information about it;
- and every update's Jacobian modified as little as possible to meet it, one observation at
  a time over the columns it touches (`constrain`): H* = H - (H N) (N^T N)^+ N^T, computed
  from an orthonormal basis of N's columns (a vehicle kilometres from the pivot, a team
  member far from the others or a long drive, squares a bad condition in N^T N). Each row
  block keeps its own columns, so the update's structure (`filters.BlockRows`) holds.
Then neither the updates nor the landmarks put back add information along N, and the
uncertainty of the team's position and heading only grows from the initial prior, as in
the exact system.

`auto` (the default, `constrained`) keeps it on when every vehicle's motion is measured (an
IMU or wheel odometry) and off when one is only extrapolated (the constant-velocity model:
the KITTI car, where clip b lost with it). It measured better with UAVs (anchored inverse
depth, simulated images and landmark mode alike), with UAVs and ground robots in one team,
and with ground robots alone on their images (`ugv2_yard` seeds 1-6: error 0.54 -> 0.17 m,
position NEES <= 6 on 10 of 12 vehicle-runs against 1), the case Huang et al. studied; in
landmark mode the ground robots lost with it (0.10 -> 0.21 m, seeds 1-3), a case with no
wrong association whose loss is not understood (BENCHMARKS.md, "Fuse: consistency (issue
15)", ninth, eleventh and twelfth steps; "Fuse: a mixed team mapped the aerial way"; "Fuse:
ground robots constrained by default").

The down translation is in the gauge only when every vehicle has a height state: a ground
robot (`OdometryModel`) drives at a known height and so pins the map's. A prior map
(`prior_map.py`) fixes the nav frame itself: there the gauge is observable and the
constraint is off.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import scipy.linalg

from cvslam_cli.estimation.motion.models import MotionModel
from cvslam_cli.records.arrays import F64, I64

# Columns of N: translations north, east, down, then the turn about the down axis.
TRANSLATIONS = ("p_n", "p_e", "p_d")
YAW_COLUMN = 3
# Singular values of a block's gauge rows below this fraction of the largest: directions it
# does not span (`constrain`).
RANK_RTOL = 1e-10
# Relative ridge on the vehicles' block when the gauge error is read from it (`gauge_correlated`).
RIDGE = 1e-12

ConstrainedSetting = Literal["auto"] | bool


def constrained(
    setting: ConstrainedSetting, motion_kinds: Sequence[str], prior_map: bool = False
) -> tuple[bool, str]:
    """Whether the setting fuse.observability_constrained keeps the gauge out of the updates
    of a team whose vehicles have motion models `motion_kinds`, and why (auto: when every
    vehicle has an IMU; never with a prior map, which fixes the nav frame: module
    docstring)."""
    on, why = _setting(setting, motion_kinds)
    if on and prior_map:
        return False, "a prior map fixes the nav frame"
    return on, why


def _setting(setting: ConstrainedSetting, motion_kinds: Sequence[str]) -> tuple[bool, str]:
    if isinstance(setting, bool):
        return setting, "fuse.observability_constrained"
    if setting != "auto":
        raise ValueError(f"observability_constrained: expected 'auto' or a bool, got {setting!r}")
    if motion_measured(motion_kinds):
        return True, "auto: every vehicle has an IMU or wheel odometry"
    return False, "auto: a vehicle without an IMU or wheel odometry"


def motion_measured(motion_kinds: Sequence[str]) -> bool:
    """Whether a team whose vehicles have these motion models (`MotionModel.kind`) is not
    empty and every vehicle's motion is measured (an IMU or wheel odometry), none only
    extrapolated (the constant-velocity model): what `auto` goes by (module docstring)."""
    return bool(motion_kinds) and all(k in ("ins", "odometry") for k in motion_kinds)


def has_down_translation(models: list[MotionModel]) -> bool:
    """Whether a shift of everything along down is unobservable: every vehicle has p_d."""
    return all("p_d" in m.state_names for m in models)


def vehicle_basis(model: MotionModel, x: F64, down: bool, pivot_ne_m: F64 | None = None) -> F64:
    """N's rows (n_v, 3 or 4) for a vehicle of `model` at state x (module docstring); the
    down column only when `down`. The turn is about the vertical through `pivot_ne_m` (north,
    east; None: the nav frame's origin). A turn about another point is this one plus a
    translation, also in the gauge, so the pivot changes N's columns, not the directions they
    span; but the turn's rows for a position p are p - pivot, and a pivot far from the
    vehicles makes the turn column nearly a multiple of a translation column, whose
    difference rounding then loses (`JointState` pivots at the team's start: `team_pivot`)."""
    names = model.state_names
    N = np.zeros((model.n, 4))
    index = {name: i for i, name in enumerate(names)}
    for axis, name in enumerate(TRANSLATIONS):
        if name in index:
            N[index[name], axis] = 1.0
    pivot = np.zeros(2) if pivot_ne_m is None else np.asarray(pivot_ne_m, dtype=float)
    # nav-frame vectors turn: positions about the pivot, velocities as directions
    for n_name, e_name, about in (("p_n", "p_e", pivot), ("v_n", "v_e", np.zeros(2))):
        if n_name in index and e_name in index:
            i, j = index[n_name], index[e_name]
            N[i, YAW_COLUMN] = -(x[j] - about[1])
            N[j, YAW_COLUMN] = x[i] - about[0]
    if "yaw" in index:
        N[index["yaw"], YAW_COLUMN] = 1.0
    return N if down else N[:, [0, 1, YAW_COLUMN]]


def team_pivot(blocks: Sequence[tuple[MotionModel, F64]]) -> F64:
    """(2,) north, east (m): the mean initial horizontal position of the vehicles (model,
    x0), the pivot of the gauge's turn (`vehicle_basis`); the origin for none. With it and
    `constrain`'s orthonormal basis, where the nav frame's origin lies (a map frame
    kilometres away, as georeferenced logs have) changes no estimate: with the turn about
    the origin, a UAV 10 km from it ended 0.23 m elsewhere than the same UAV at it
    (BENCHMARKS.md, "Fuse: the gauge's turn about the team's start")."""
    starts = [model.pose(x0)[0][:2] for model, x0 in blocks]
    return np.mean(starts, axis=0) if starts else np.zeros(2)


def constrain(H: F64, N: F64) -> F64:
    """H* (..., m, c) = H - (H N) (N^T N)^+ N^T: the smallest change (Frobenius) to the rows
    H (..., m, c) over columns whose gauge rows are N (..., c, g) after which H* N = 0.
    Computed as H - (H U) U^T with U an orthonormal basis of N's columns (its left singular
    vectors of a singular value above RANK_RTOL of the largest): the same projection, but
    N^T N squares N's condition, and a vehicle far from the gauge's pivot (kilometres: its
    turn column nearly a multiple of a translation column) made the squared form leak
    information along the gauge in rounding."""
    U, s, _ = np.linalg.svd(N, full_matrices=False)
    U = U * (s > RANK_RTOL * s[..., :1])[..., None, :]  # drop what N does not span
    return H - (H @ U) @ np.swapaxes(U, -1, -2)


def gauge_correlated(
    P: F64, N: F64, N_m: F64, C: F64, groups: Sequence[tuple[I64, I64]]
) -> tuple[F64, F64]:
    """Points put back into the state with marginals C (k, 3, 3) and gauge rows N_m
    (k, 3, g) that add no information about the gauge: m = m_true + N_m g + w, with w
    independent and g the gauge error of the point's group of vehicles as their states read
    it. `groups`: (the points j, the state rows v of their group's vehicles), one per group.
    Per group, g is the weighted least-squares estimate g = L x from the error of those
    vehicles' blocks,
        L = A^-1 N_v^T P_vv^-1 E_v,   A = N_v^T P_vv^-1 N_v,
    so that L N = I. Any L with L N = I makes a point a new state y = N_m L x + w whose
    gauge rows N_m L N = N_m are the ones it carries, and such a state leaves N^T P^-1 N as
    it was (the point tells nothing about where the team is or which way it faces).
    Which vehicles: a group is the vehicles linked to the point's observers by landmarks
    they observed (`mapping.LandmarkBook.group`). Vehicles that have shared no landmark have
    a gauge each (the constraint keeps each one, since every update touches one vehicle's
    columns and its landmarks'), and a point read from every vehicle would be correlated
    with vehicles its group never met: its later observations would then move them (two
    ground robots kept from sharing a landmark reached a correlation of 0.5 between their
    poses). Within a group, all its vehicles: they carry almost all of what the state
    knows about its gauge (their initial prior; on `uav2_paper` the standard deviations of
    their estimate are 5-20 % above those of the whole state's, A = N^T P^-1 N, and the
    errors of the runs the same: BENCHMARKS.md, "Fuse: consistency (issue 15)"), where the
    observers alone read it less precisely (`uav2_paper` with images: 5 % larger errors,
    BENCHMARKS.md "Fuse: a landmark put back, tied to its group of vehicles"). It costs
    O(n_v^3 + g n_v n) a group, where the whole state's A costs a Cholesky factorisation of
    P, O(n^3).
    Returns P_mm (3k, 3k) = N_m L P L^T N_m^T + blockdiag(W) (per group L P L^T = A^-1;
    between groups a and b, L_a P L_b^T = A_a^-1 N_a^T P_aa^-1 P_ab P_bb^-1 N_b A_b^-1, zero
    where the groups share nothing) with W = C - (N_m L P L^T N_m^T)_jj (clipped to be
    positive semi-definite: where the vehicles know the gauge worse than C, the point is
    less certain than C) and the cross-covariance P_mx = N_m L P (3k, n)."""
    k, g = len(N_m), N.shape[1]
    parts = []  # per group: its points' rows of P_mm, N_m there, v, P_vv^-1 N_v, A^-1, L P
    for points, v in groups:
        P_vv = P[np.ix_(v, v)]
        # P_vv is positive definite (prior and process noise); a tiny ridge keeps rounding in
        # the updates from making it look otherwise to the Cholesky solve
        ridge = RIDGE * float(np.max(np.diagonal(P_vv)))
        X = scipy.linalg.solve(P_vv + ridge * np.eye(len(v)), N[v], assume_a="pos")
        A = N[v].T @ X
        S = np.linalg.inv(0.5 * (A + A.T))
        rows = (3 * np.asarray(points)[:, None] + np.arange(3)).ravel()
        parts.append((rows, N_m[points].reshape(3 * len(points), g), v, X, S, S @ (X.T @ P[v])))
    P_mx = np.empty((3 * k, P.shape[0]))
    P_mm = np.empty((3 * k, 3 * k))
    for a, (rows_a, Nm_a, _, _, S_a, LP_a) in enumerate(parts):
        P_mx[rows_a] = Nm_a @ LP_a
        for b, (rows_b, Nm_b, v_b, X_b, S_b, _) in enumerate(parts):
            LPLt = S_a if a == b else LP_a[:, v_b] @ X_b @ S_b
            P_mm[np.ix_(rows_a, rows_b)] = Nm_a @ LPLt @ Nm_b.T
    for j in range(k):
        b = slice(3 * j, 3 * j + 3)
        w, V = np.linalg.eigh(C[j] - P_mm[b, b])
        P_mm[b, b] += (V * np.maximum(w, 0.0)) @ V.T
    return 0.5 * (P_mm + P_mm.T), P_mx
