"""Data association: which stereo matches of a frame are re-observations of mapped landmarks,
and the paper's feature types 1/2/3 (`classify`: their one definition).

The stereo constraint of extract, applied over time: every landmark in the state is predicted
into both images with the observation model (eq. 19) and its innovation covariance

    S_j = H_j P H_j^T + R,     H_j = [H_v,j  H_m,j]  (the vehicle block and landmark j only)

and a stereo match z_i (u_l, v_l, u_r, v_r) is a candidate for landmark j only inside that
landmark's innovation window, the chi-square gate d2_ij = (z_i - z_j)^T S_j^-1 (z_i - z_j) <
chi2_4(p). Among its candidates a landmark takes the one with the smallest descriptor
distance D1, if D1 < ratio * D2 (second smallest in the window) and D1 < max_distance; a match
claimed by several landmarks goes to the smallest D1. For a landmark the observing vehicle
has not seen yet (another vehicle's, `descriptor_tests`) D2 may be taken over every match of
the frame instead (`frame_wide`): the gate of a view from elsewhere is wide, and a look-alike
on a repeated texture (bricks, shelves, windows) can be alone in it, where a ratio test
over the window has nothing to compare with; over the frame its twins make it fail.
Everything is vectorised over landmarks x matches (a frame has ~100 landmarks in view and a
few hundred matches); the full d2 is computed only for the pairs whose match lies inside its
landmark's window's bounding box (`_in_boxes`, a necessary condition of the gate): the same
decisions at a fraction of the pairs.

Which landmarks are predicted at all (`visible_slots`): in front of the cameras, inside both
images, and viewed from within the maximum angle of their mean viewing direction
(`mapping.LandmarkBook.seen_from`); one the observing vehicle has never observed also from
within a factor of the distance it was observed from (`mapping.LandmarkBook.
ids_within_distance`, `other_vehicle_max_distance_ratio`). SIFT finds a point again over a
range of scales, but a view from several times nearer or farther resolves other detail of
the surface: the keypoint it finds is often another point, or the same one displaced by a
bias that no frame averages out. Checked against the simulator's true depth on the mixed
team (UAVs 8 m up over a yard two ground robots drive through): of the cross-vehicle
observations made from 1-2x the distance the landmark was mapped from, 1-6 % are of another
point; from 2-2.8x 3 %, 2.8-4x 19 %, beyond 4x 68 % (BENCHMARKS.md, "Fuse: the first
encounter, and three designs measured against it"; the limit's effect: "Fuse: another
vehicle's landmark, from about its distance"). A vehicle's own landmarks are not limited: it
tracks them through every distance in between.

Feature types (paper, section "Cooperative VSLAM"), for the M stereo matches of a frame of
vehicle v (`classify`):
- type 1: associated with a landmark in the state that v has observed before (a
  re-observation; after more than `loop_closure_gap_ns` without one, a loop closure);
- type 2: associated with a landmark in the state that v observes for the first time: one
  mapped by other vehicles (what makes cooperation pay);
- type 3: inside no landmark's window and not associated: new; a candidate for the map
  (`new_landmarks.py`);
- 0: inside some landmark's window but not used this frame (failed the descriptor or
  consistency test, or beyond the per-frame update limit): neither updates nor starts a
  landmark (it could duplicate one).
Types 1 and 2 update the state; type 3 is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cvslam_cli.estimation.mapping import NEVER, LandmarkBook
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehicleInput, VehiclePose, VehicleRun
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.records.arrays import F64, I64

TYPE_1, TYPE_2, TYPE_3 = 1, 2, 3


@dataclass(frozen=True, eq=False)
class LandmarkPrediction:
    """k landmarks predicted into a stereo frame: `slots` (k,), `z` (k, 4) predicted pixels
    (u_l, v_l, u_r, v_r), `H_v` (k, 4, n_v) w.r.t. the vehicle block, `H_m` (k, 4, d)
    w.r.t. the landmark's d columns in the state (`JointState.landmark_columns`), `S` (k, 4, 4)
    innovation covariances; `rectified`: the rig predicts v_l = v_r, so that an update may
    use the three rows of `observation.mean_v_rows`; `noise_scale` (k,): each observation's
    pixel noise variance over the filter's (`noise_scale`; None: 1 for all), in S already."""

    slots: I64
    z: F64
    H_v: F64
    H_m: F64
    S: F64
    rectified: bool = False
    noise_scale: F64 | None = None


@dataclass(frozen=True, eq=False)
class LandmarkErrors:
    """k landmarks' covariance blocks (over their d columns in the state) with the observing
    vehicle's n_v states: P_vm (k, n_v, d) and their own P_mm (k, d, d). A landmark's error
    splits into the part that follows the vehicle's and the rest (`given_vehicle`); out of the
    state (no cross-covariance with the vehicle, `independent`) it is all the rest."""

    P_vm: F64
    P_mm: F64

    def given_vehicle(self, P_vv: F64, rows: I64) -> tuple[F64, F64]:
        """For the landmarks `rows` (a,): dm_j = G_j dx_v + e_j with G (a, d, n_v) =
        P_mv P_vv^-1 and e_j independent of dx_v, of covariance (a, d, d) P_mm - P_mv P_vv^-1
        P_vm (the landmark's covariance given the vehicle's state); (G, that covariance)."""
        P_vm = self.P_vm[rows]
        a, n_v, d = P_vm.shape
        X = np.linalg.solve(P_vv, P_vm.transpose(1, 0, 2).reshape(n_v, a * d))  # P_vv^-1 P_vm
        G = X.reshape(n_v, a, d).transpose(1, 2, 0)
        cov = self.P_mm[rows] - G @ P_vm
        return G, 0.5 * (cov + np.swapaxes(cov, 1, 2))

    @staticmethod
    def independent(P_mm: F64, n_v: int) -> LandmarkErrors:
        """Landmarks of covariance P_mm (k, d, d) uncorrelated with the vehicle's n_v states."""
        return LandmarkErrors(np.zeros((len(P_mm), n_v, P_mm.shape[1])), P_mm)


@dataclass(frozen=True, eq=False)
class Association:
    """a accepted pairs: `pred_index` (a,) rows of the prediction, `match_index` (a,) rows of
    the frame's matches, `d2` (a,) Mahalanobis distances, `descriptor_distance` (a,);
    `near_landmark` (M,) bool: the match lies inside some landmark's window (accepted or not),
    so it must not start a new landmark (it would duplicate one)."""

    pred_index: I64
    match_index: I64
    d2: F64
    descriptor_distance: F64
    near_landmark: NDArray[np.bool_]


def camera_depths(obs: StereoObservationModel, p_nav_m: F64, euler_rad: F64, m_nav_m: F64) -> F64:
    """(N,) depth of landmarks m (N, 3) in the left camera."""
    C = euler_zyx_to_matrix(*euler_rad)
    q = (np.atleast_2d(m_nav_m) - p_nav_m) @ C
    return (q - obs.t_body_cam[0]) @ obs.R_cam_body[0][2]


def predict_landmarks(
    pose: VehiclePose,
    slots: I64,
    m_nav_m: F64,
    P_vm: F64,
    P_mm: F64,
    R: F64,
    M: F64 | None = None,
    noise_scale: F64 | None = None,
) -> LandmarkPrediction:
    """Predict landmarks m (k, 3) seen from the vehicle at `pose` (its observation model and
    d z / d x_v, `VehiclePose.vehicle_jacobian`). P_vm (k, n_v, d), P_mm (k, d, d):
    covariance blocks of the landmarks' d state columns, with d m / d columns = M (k, 3, d)
    (None: the identity, the columns are m); H_m (k, 4, d) is w.r.t. those columns; R (4, 4)
    the pixel noise, times `noise_scale` (k,) per landmark when given (`noise_scale`)."""
    obs, P_vv = pose.obs, pose.P_vv
    z, H_pose, H_m = obs.predict(pose.p_nav_m, pose.euler_rad, m_nav_m)
    if M is not None:
        H_m = H_m @ M
    H_v = pose.vehicle_jacobian(H_pose)
    HvPvm = H_v @ P_vm  # (k, 4, d)
    cross = HvPvm @ np.swapaxes(H_m, 1, 2)
    S = (
        H_v @ P_vv @ np.swapaxes(H_v, 1, 2)
        + cross
        + np.swapaxes(cross, 1, 2)
        + H_m @ P_mm @ np.swapaxes(H_m, 1, 2)
        + scaled_noise(R, noise_scale)
    )
    return LandmarkPrediction(
        np.asarray(slots, dtype=np.int64), z, H_v, H_m, S, obs.rectified, noise_scale
    )


def scaled_noise(R: F64, noise_scale: F64 | None) -> F64:
    """The pixel noise R (4, 4) of k observations: R itself (None: every one alike) or
    (k, 4, 4), observation j's scaled by noise_scale[j] (`noise_scale`)."""
    return R if noise_scale is None else noise_scale[:, None, None] * R


def noise_scale(book: LandmarkBook, ids: I64, vehicle: int, ratio: float) -> F64 | None:
    """(k,) each landmark's pixel noise variance over the filter's when `vehicle` observes
    it: `ratio` (`SlamSettings.other_vehicle_noise_ratio`) where another vehicle has observed
    the landmark, 1 where only this one has; None when the ratio is 1 (every observation
    alike). Another vehicle's view of the ground (another height, heading, camera), and what
    it carries of the other vehicle's errors, weighed less than the next frame of the same
    camera, whose scatter the measured pixel noise is (BENCHMARKS.md, "Fuse: another
    vehicle's view, its own pixel noise": its innovations are only 10-70 % larger)."""
    if ratio <= 1.0:
        return None
    seen = book.last_seen_ns[ids] != NEVER  # (k, vehicles)
    seen[:, vehicle] = False
    return np.where(seen.any(axis=1), ratio, 1.0)


def descriptor_tests(
    book: LandmarkBook,
    ids: I64,
    vehicle: int,
    own_ratio: float,
    other_ratio: float,
    other_over_frame: bool,
) -> tuple[F64, NDArray[np.bool_]]:
    """The descriptor ratio test of each landmark `ids` (k,) when `vehicle` observes it:
    (ratio (k,), frame_wide (k,), `associate`'s arguments). A landmark it never observed
    (another vehicle's, seen from elsewhere) gets `other_ratio` (the stricter) and, with
    `other_over_frame`, its second-best distance over the whole frame; one it did,
    `own_ratio` within its window (BENCHMARKS.md, "Another vehicle's landmarks, a stricter
    descriptor test", "Fuse: another vehicle's landmark, distinct in the whole frame"). The
    frame's association and re-activation both use it."""
    new_to_me = book.unseen_by(ids, vehicle)
    return np.where(new_to_me, other_ratio, own_ratio), new_to_me & other_over_frame


def lookalike_bound(per_mpx: float) -> float:
    """The bound on d2 + ln det S_l of `lookalike_gates` for a density of look-alikes of
    `per_mpx` per megapixel (inf for 0: no bound): -2 ln(2 pi lambda), lambda per px^2."""
    return float("inf") if per_mpx <= 0 else float(-2.0 * np.log(2.0 * np.pi * per_mpx * 1e-6))


def lookalike_gates(
    book: LandmarkBook, ids: I64, vehicle: int, S: F64, gate_chi2: float, bound: float
) -> F64:
    """The chi-square gate of each landmark `ids` (k,) when `vehicle` observes it, S (k, 4, 4)
    its innovation covariance: `gate_chi2` for a landmark the vehicle observed before; for one
    it never observed (another vehicle's) also d2 < bound - ln det S_l, S_l the left image's
    (u, v) block. The likelihood-ratio test of the match being the landmark against a
    look-alike (a repeated texture that passes the descriptor tests) spread at a density
    lambda about it, bound = -2 ln(2 pi lambda) (`lookalike_bound`; Bar-Shalom's clutter
    model; a repeated texture puts its look-alikes near the original, so lambda is the
    density there, not the image's average): a window of area ~ sqrt(det S_l) holds a
    look-alike the more often the larger it is, so the match must lie the closer to the
    prediction. A vehicle's first sighting of another's landmark comes with the widest
    windows (its pose relative to that map is known only from its prior or a distant link),
    and its wrong ones are there: on the mixed team's images, the first associations with d2
    + ln det S_l above 14 were 54 % wrong against the true depth, those below 10 4 %
    (BENCHMARKS.md, "Fuse: another vehicle's landmark, inside a window that a look-alike
    would fill"). The right coordinates' spread given the left's (the pixel noise) is about
    the same for every match and folds into the bound."""
    gates = np.full(len(ids), gate_chi2)
    if not np.isfinite(bound):
        return gates
    new_to_me = book.unseen_by(ids, vehicle)
    if new_to_me.any():
        logdet = np.linalg.slogdet(S[new_to_me][:, :2, :2])[1]
        gates[new_to_me] = np.minimum(gate_chi2, bound - logdet)
    return gates


def in_view(z: F64, depth_m: F64, size_px: NDArray[np.int64], margin_px: float = 0.0) -> NDArray:
    """(k,) bool: in front of the camera and inside both images (size_px (2, 2) width,
    height of left and right)."""
    ok = depth_m > 0
    for c in range(2):
        u, v = z[:, 2 * c], z[:, 2 * c + 1]
        w, h = size_px[c]
        ok &= (u >= -margin_px) & (u < w + margin_px) & (v >= -margin_px) & (v < h + margin_px)
    return ok


def descriptor_distances(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> NDArray[np.float32]:
    """(k, M) Euclidean distances between descriptors a (k, D) and b (M, D)."""
    af = a.astype(np.float32)
    bf = b.astype(np.float32)
    d2 = (af * af).sum(1)[:, None] + (bf * bf).sum(1)[None, :] - 2.0 * (af @ bf.T)
    return np.sqrt(np.maximum(d2, 0.0))


def _in_boxes(pred: LandmarkPrediction, z_obs: F64, gate_chi2: float) -> NDArray[np.bool_]:
    """(k, M) whether match i lies inside landmark j's window's bounding box in the left
    image: |z_i,c - z_j,c| <= sqrt(gate S_j,cc) for c = u_l, v_l. A necessary condition of
    the gate (for S positive definite, d2 >= (z_i,c - z_j,c)^2 / S_j,cc for every c), with a
    margin of 1e-6 for rounding, so that the full d2 is computed only where it can pass: a
    frame's windows cover a small part of its image."""
    out = np.ones((len(pred.z), len(z_obs)), dtype=bool)
    for c in range(2):
        half = np.sqrt(gate_chi2 * pred.S[:, c, c]) * (1.0 + 1e-6)
        out &= np.abs(z_obs[None, :, c] - pred.z[:, None, c]) <= half[:, None]
    return out


def associate(
    pred: LandmarkPrediction,
    landmark_desc: NDArray[np.uint8],
    z_obs: F64,
    obs_desc: NDArray[np.uint8],
    gate_chi2: float,
    ratio: float | F64,
    max_distance: float,
    frame_wide: bool | NDArray[np.bool_] = False,
    accept_chi2: F64 | None = None,
) -> Association:
    """Match predicted landmarks (k) with a frame's stereo matches z_obs (M, 4) (module
    docstring); `ratio`: the descriptor ratio, one for all or one per landmark (k,);
    `frame_wide`, for all or per landmark: the ratio test's second-best distance over all M
    matches, not only those inside the landmark's window; `accept_chi2` (k,): each
    landmark's own gate, at most `gate_chi2` (`lookalike_gates`), for its candidates (a match
    inside `gate_chi2` but beyond it is still near the landmark: it starts none)."""
    k, M = len(pred.z), len(z_obs)
    if k == 0 or M == 0:
        e = np.zeros(0, dtype=np.int64)
        return Association(e, e, np.zeros(0), np.zeros(0), np.zeros(M, dtype=bool))
    # only the pairs inside their landmark's window's bounding box
    lm_at, obs_at = np.nonzero(_in_boxes(pred, z_obs, gate_chi2))
    d2 = np.full((k, M), np.inf)
    if len(lm_at):
        lm_in, at = np.unique(lm_at, return_inverse=True)
        S_inv = np.linalg.inv(pred.S[lm_in])[at]  # (p, 4, 4), symmetric
        diff = z_obs[obs_at] - pred.z[lm_at]  # (p, 4)
        d2[lm_at, obs_at] = np.sum((diff[:, None, :] @ S_inv)[:, 0] * diff, axis=1)
    near = (d2 < gate_chi2).any(axis=0)
    gated = d2 < (gate_chi2 if accept_chi2 is None else np.asarray(accept_chi2)[:, None])
    rows = np.flatnonzero(gated.any(axis=1))
    if len(rows) == 0:
        e = np.zeros(0, dtype=np.int64)
        return Association(e, e, np.zeros(0), np.zeros(0), near)
    cols = np.flatnonzero(near)
    D = descriptor_distances(landmark_desc[rows], obs_desc[cols])
    D = np.where(gated[np.ix_(rows, cols)], D, np.inf)
    best = np.argmin(D, axis=1)
    best_d = D[np.arange(len(rows)), best]
    second_d = np.partition(D, 1, axis=1)[:, 1] if D.shape[1] >= 2 else np.full(len(rows), np.inf)
    wide = np.broadcast_to(np.asarray(frame_wide, dtype=bool), (k,))[rows]
    if wide.any():  # the second-best over every match (the window's are among them)
        D_all = descriptor_distances(landmark_desc[rows[wide]], obs_desc)
        D_all[np.arange(len(D_all)), cols[best[wide]]] = np.inf
        second_d[wide] = D_all.min(axis=1)
    r = ratio if np.isscalar(ratio) else np.asarray(ratio)[rows].astype(second_d.dtype)
    ok = (best_d < max_distance) & (best_d < r * second_d)
    lm = rows[ok]
    mi = cols[best[ok]]
    dd = best_d[ok].astype(float)
    # one landmark per match: the smallest descriptor distance wins
    order = np.argsort(dd, kind="stable")
    _, first = np.unique(mi[order], return_index=True)
    keep = order[first]
    keep.sort()
    return Association(lm[keep], mi[keep], d2[lm[keep], mi[keep]], dd[keep], near)


def spread_order(uv_px: F64, priority: F64, size_px: tuple[int, int], grid: int = 4) -> I64:
    """Order points for selection so that the first ones cover the image: a `grid` x `grid`
    bucketing, round-robin over buckets, each bucket in increasing `priority` (lower first).
    Returns indices into uv_px (N, 2)."""
    n = len(uv_px)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    w, h = size_px
    bx = np.clip((uv_px[:, 0] * grid / max(w, 1)).astype(np.int64), 0, grid - 1)
    by = np.clip((uv_px[:, 1] * grid / max(h, 1)).astype(np.int64), 0, grid - 1)
    bucket = by * grid + bx
    order = np.lexsort((priority, bucket))
    b_sorted = bucket[order]
    starts = np.flatnonzero(np.r_[True, b_sorted[1:] != b_sorted[:-1]])
    rank = np.arange(n) - np.repeat(starts, np.diff(np.r_[starts, n]))
    return order[np.lexsort((priority[order], rank))]


def pose_consistent(
    pred: LandmarkPrediction,
    rows: I64,
    z_obs: F64,
    P_vv: F64,
    errors: LandmarkErrors,
    R: F64,
    gate_chi2: float,
    iterations: int = 3,
) -> NDArray[np.bool_]:
    """Which associations (prediction rows `rows`, observations z_obs (a, 4)) agree with one
    common vehicle correction. Individually gated innovations can still be wrong matches:
    the windows are wide while the pose is uncertain, and a repetitive texture offers a
    look-alike inside them. The innovations of right matches are explained by one small
    correction dx of the vehicle state: with the landmarks' errors dm_j = G_j dx + e_j
    (`errors.given_vehicle`: the part that follows the vehicle's error and the rest),
    nu_j = (H_v,j + H_m,j G_j) dx + (landmark and pixel noise with covariance W_j^-1 =
    H_m,j C_j H_m,j^T + R); dx is the weighted least-squares solution with the prior P_vv,
    and a match whose residual fails the chi-square gate is dropped, re-solving without it
    (`iterations` times). A landmark mapped from this vehicle's pose shares most of its
    error: its own rest C_j is its triangulation's, not the pose's uncertainty it inherited,
    so a look-alike several pixels off stands out even while the pose is uncertain. R (4, 4),
    times the prediction's `noise_scale` where it has one."""
    a = len(rows)
    keep = np.ones(a, dtype=bool)
    if a == 0:
        return keep
    G, C = errors.given_vehicle(P_vv, rows)
    H_m = pred.H_m[rows]
    H_v = pred.H_v[rows] + H_m @ G
    nu = z_obs - pred.z[rows]
    scale = None if pred.noise_scale is None else pred.noise_scale[rows]
    W = np.linalg.inv(H_m @ C @ np.swapaxes(H_m, 1, 2) + scaled_noise(R, scale))  # (a, 4, 4)
    HtW = np.swapaxes(H_v, 1, 2) @ W  # (a, n_v, 4)
    info_prior = np.linalg.inv(P_vv)
    for _ in range(iterations):
        A = info_prior + np.sum(HtW[keep] @ H_v[keep], axis=0)
        b = np.sum(HtW[keep] @ nu[keep][:, :, None], axis=0)[:, 0]
        dx = np.linalg.solve(A, b)
        r = nu - H_v @ dx
        d2 = np.sum((r[:, None, :] @ W)[:, 0] * r, axis=1)
        new_keep = d2 < gate_chi2
        if np.array_equal(new_keep, keep) or not new_keep.any():
            break
        keep = new_keep
    return keep


@dataclass(frozen=True, eq=False)
class FeatureTypes:
    """A frame's M matches classified (module docstring): `type` (M,) 0 / 1 / 2 / 3; for the
    k associated ones (the rows given to `classify`, in its order): `absent_ns` (k,) since
    the vehicle last observed the landmark (0 for type 2) and `loop_closure` (k,) type 1
    after more than the loop-closure gap."""

    type: NDArray[np.int8]
    absent_ns: I64
    loop_closure: NDArray[np.bool_]

    def count(self, t: int) -> int:
        return int(np.sum(self.type == t))


def absence_ns(last_seen_ns: I64, t_ns: int) -> I64:
    """(k,) time since the vehicle last observed each landmark (0: never observed it)."""
    return np.where(last_seen_ns != NEVER, t_ns - last_seen_ns, 0)


def classify(
    near: NDArray[np.bool_],
    match_rows: I64 | None = None,
    last_seen_ns: I64 | None = None,
    t_ns: int = 0,
    loop_gap_ns: int = 0,
) -> FeatureTypes:
    """The feature types of a frame's matches (module docstring). near (M,): inside some
    landmark's window; match_rows (k,): the matches used to update (none: None), associated
    with landmarks the vehicle last observed at last_seen_ns (k,) (`mapping.NEVER`: never),
    at time t_ns."""
    if match_rows is None or last_seen_ns is None:
        match_rows = last_seen_ns = np.zeros(0, dtype=np.int64)
    seen_before = last_seen_ns != NEVER
    types = np.where(near, 0, TYPE_3).astype(np.int8)
    types[match_rows] = np.where(seen_before, TYPE_1, TYPE_2)
    absent = absence_ns(last_seen_ns, t_ns)
    return FeatureTypes(types, absent, seen_before & (absent > loop_gap_ns))


def unassociated(n_matches: int) -> FeatureTypes:
    """The types of a frame's matches when none is associated: all type 3."""
    return classify(np.zeros(n_matches, dtype=bool))


def in_view_rows(vin: VehicleInput, p: F64, euler: F64, m_nav_m: F64) -> I64:
    """Rows of landmarks m (k, 3) predicted in front of vin's cameras at (p, Psi) and inside
    both images (a point near the camera plane projects far outside: its Jacobian would
    blow up the innovation covariance)."""
    if not len(m_nav_m):
        return np.zeros(0, dtype=np.int64)
    depth = camera_depths(vin.obs, p, euler, m_nav_m)
    front = np.flatnonzero(depth > 0)
    if not len(front):
        return front
    z_pred = vin.obs.project(p, euler, m_nav_m[front])
    return front[in_view(z_pred, depth[front], vin.features.rig.size_px)]


def view_rays(vin: VehicleInput, p: F64, euler: F64, m_nav_m: F64) -> tuple[F64, F64]:
    """(k, 3) unit vectors from landmarks m (k, 3) to vin's left camera centre at (p, Psi),
    and their lengths (k,) (m)."""
    centre = vin.obs.left_camera_centre(p, euler)
    d = centre - np.atleast_2d(m_nav_m)
    distance = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    return d / distance[:, None], distance


def visible_slots(
    state: JointState,
    book: LandmarkBook,
    run: VehicleRun,
    pose: VehiclePose,
    max_angle_rad: float,
    max_distance_ratio: float,
) -> I64:
    """Slots of the landmarks in the state predicted in view of run's vehicle at `pose`
    (module docstring)."""
    vin = run.vin
    p, euler = pose.p_nav_m, pose.euler_rad
    m_all = state.landmarks()
    slots = in_view_rows(vin, p, euler, m_all)
    views, distance = view_rays(vin, p, euler, m_all[slots])
    ids = book.slot_ids[slots]
    return slots[
        book.ids_viewable(
            ids, run.index, views, distance, np.cos(max_angle_rad), max_distance_ratio
        )
    ]


def record_observations(
    state: JointState, book: LandmarkBook, run: VehicleRun, slots: I64, stamp_ns: int, z: F64
) -> None:
    """Book that run's vehicle observed the landmarks in `slots` at its current pose, with
    the measurements z (k, 4) (kept in its observation log)."""
    vin = run.vin
    p, euler = vin.model.pose(state.vehicle_x(vin.name))
    views, distance = view_rays(vin, p, euler, state.landmarks(slots))
    book.observe(book.slot_ids[slots], run.index, stamp_ns, views, distance)
    run.observations.add(stamp_ns, book.slot_ids[slots], z)


def predict_in_state(
    state: JointState,
    pose: VehiclePose,
    slots: I64,
    R_hat: F64,
    noise_scale: F64 | None = None,
) -> tuple[LandmarkPrediction, LandmarkErrors]:
    """The state's landmarks in `slots` predicted into the images of the vehicle at `pose`, with
    their innovation covariances (R_hat (4, 4) the pixel noise as the filter scales it, times
    `noise_scale` (k,) per landmark when given); also their covariance blocks with the
    vehicle (`LandmarkErrors`, over their columns in the state, `JointState.landmark_columns`:
    what the prediction's H_m is the Jacobian for)."""
    cols = state.landmark_columns(slots)  # (k, d)
    P = state.P
    P_vm = P[pose.index[:, None, None], cols[None, :, :]].transpose(1, 0, 2)
    P_mm = P[cols[:, :, None], cols[:, None, :]]
    m, M = state.landmarks_nav(slots)
    pred = predict_landmarks(pose, slots, m, P_vm, P_mm, R_hat, M, noise_scale)
    return pred, LandmarkErrors(P_vm, P_mm)
