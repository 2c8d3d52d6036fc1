"""Trajectory metrics computed exactly as evo (github.com/MichaelGrupp/evo, 1.38) computes them.

Pure numpy on `PoseTable`s (no file I/O); evo is never imported here, the tests compare
against it. Every function first associates the two tables by time (`associate`, evo's
`sync.associate_trajectories`), then works on the K matched pairs (ref_k, est_k), poses
T_k = [R_k | p_k] with R_k from the (normalised) quaternion.

Statistics of an error vector e (K,), as evo's `PE.get_statistic`:
    rmse = sqrt(mean(e^2)),  mean,  median,  std = sqrt(mean((e - mean)^2))  (population),
    min,  max,  sse = sum(e^2).

APE, translation part (`evo_ape -r trans_part [--align] [--correct_scale]`):
    e_k = | A(p_est_k) - p_ref_k |,   A = Umeyama alignment (identity, se3 or sim3) of the
    matched est positions onto the ref positions (`align.umeyama`).

RPE, translation part (`evo_rpe -r trans_part --delta D --delta_unit m|f [--all_pairs]`):
for each index pair (i, j) of the matched sequence,
    E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j),   e_ij = | trans(E_ij) |,
Q the ref poses, P the (aligned: R -> R_a R, p -> s R_a p + t_a) est poses, T^-1 = [R^T | -R^T p].
The pairs come from the *estimate's* poses unless `pairs_from_reference` (evo's default):
  * frames, consecutive:  i = 0, D, 2D, ...,  j = i + D;
  * frames, all pairs:    every i with i + D < K, j = i + D;
  * metres, consecutive:  walk the poses summing the step lengths |p_k - p_{k-1}|; when the sum
    reaches D (>=) the pose closes a pair with the previous selected one and the sum restarts
    at 0 (first pose always selected);
  * metres, all pairs:    for every i < K-1, with d the accumulated path distances,
    j = i + 1 + argmin_k |(d[i+1+k] - d[i]) - D| (first minimum), kept only when that
    |(d[j] - d[i]) - D| <= tol = rel_delta_tol * D (evo's default rel_delta_tol 0.1). The
    tolerance is used only in all-pairs mode, as in evo.

Where evo's definitions surprise:
  * association walks the table with fewer poses (the estimate when both have as many) and
    lets the longer one's poses be used twice or skipped; a tie goes to the earlier stamp;
  * RPE pairs are chosen on the estimate's (aligned) path by default, so a sim3 scale changes
    which poses pair up; consecutive metre pairs close at the first pose whose summed step
    lengths reach delta (so they are >= delta long), all-pairs ones may be up to 10 % shorter
    or longer than delta, including near the end of the path;
  * se3 alignment cannot change the RPE (it is rigid), sim3 scales the estimate's steps;
  * evo uses the 3x3 blocks of a KITTI file as written, which are up to ~2e-7 from a rotation;
    `read_kitti` re-orthonormalises them, so RPE on KITTI files read by evo itself agrees to
    ~1e-6 relative (1e-7 m per metre of pair span), and exactly (1e-10) on the same poses.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.stats import chi2

from cvslam_cli.evaluation.align import IDENTITY, Alignment, umeyama
from cvslam_cli.geometry.rotations import quat_xyzw_to_matrix
from cvslam_cli.records.arrays import F64, I64
from cvslam_cli.records.poses import PoseTable

AlignKind = Literal["none", "se3", "sim3"]
DeltaUnit = Literal["m", "frames"]

#: evo's default association tolerance, `max_diff` = 0.01 s.
DEFAULT_MAX_DIFF_NS = 10_000_000


# -- association ----------------------------------------------------------------------------


def _match_stamps(short_ns: I64, long_ns: I64, max_diff_ns: int) -> tuple[I64, I64]:
    """evo `sync.matching_time_indices` (offset 0) on integer nanoseconds: for each stamp of
    `short_ns`, the nearest stamp of `long_ns` when |difference| <= max_diff_ns. For sorted
    `long_ns` with the bracketing stamps lo <= s <= hi, the upper one wins only when strictly
    nearer (a tie goes to the lower); unsorted `long_ns`: the first minimum of |long - s|."""
    short_ns = np.asarray(short_ns, dtype=np.int64)
    long_ns = np.asarray(long_ns, dtype=np.int64)
    empty = np.empty(0, dtype=np.int64)
    if len(short_ns) == 0 or len(long_ns) == 0:
        return empty, empty.copy()
    if np.any(np.diff(long_ns) < 0):
        best = np.array([int(np.argmin(np.abs(long_ns - s))) for s in short_ns], dtype=np.int64)
        ok = np.abs(long_ns[best] - short_ns) <= max_diff_ns
        return np.flatnonzero(ok).astype(np.int64), best[ok]
    n = len(long_ns)
    upper = np.minimum(np.searchsorted(long_ns, short_ns, side="right"), n - 1)
    diff_ub = long_ns[upper] - short_ns
    has_lower = upper > 0
    diff_lb = np.where(has_lower, short_ns - long_ns[np.maximum(upper - 1, 0)], 0)
    in_range = (short_ns >= long_ns[0] - max_diff_ns) & (short_ns <= long_ns[-1] + max_diff_ns)
    take_upper = (diff_ub <= max_diff_ns) & (~has_lower | (diff_ub < diff_lb))
    take_lower = ~take_upper & has_lower & (diff_lb <= max_diff_ns) & (diff_lb <= diff_ub)
    ok = in_range & (take_upper | take_lower)
    best = np.where(take_upper, upper, upper - 1)
    return np.flatnonzero(ok).astype(np.int64), best[ok].astype(np.int64)


def associate(
    ref: PoseTable, est: PoseTable, max_diff_ns: int = DEFAULT_MAX_DIFF_NS
) -> tuple[I64, I64]:
    """Match poses by time as evo's `sync.associate_trajectories(ref, est, max_diff)`:
    returns (ref_idx (K,), est_idx (K,)) into the two tables.

    The table with fewer poses (`est` when both have as many) is walked in order; each of its
    stamps takes the nearest stamp of the other table when |t_long - t_short| <= max_diff_ns,
    else it is dropped. Poses of the longer table may therefore be used twice or not at all.
    Exact in integer ns (evo compares float seconds, which can differ only at |diff| within
    float rounding of max_diff). Raises ValueError when nothing matches (evo SyncException)."""
    if max_diff_ns < 0:
        raise ValueError(f"max_diff_ns must be >= 0, got {max_diff_ns}")
    est_longer = len(est) > len(ref)
    short, long = (ref, est) if est_longer else (est, ref)
    idx_short, idx_long = _match_stamps(short.stamps_ns, long.stamps_ns, int(max_diff_ns))
    if len(idx_short) == 0:
        raise ValueError(
            f"found no matching timestamps between the reference ({len(ref)} poses) and the "
            f"estimate ({len(est)} poses) with max. time diff {max_diff_ns} ns"
        )
    return (idx_short, idx_long) if est_longer else (idx_long, idx_short)


# -- statistics -----------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorStatistics:
    """evo's statistics of an error vector e (K,), K >= 1 (see the module docstring)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float

    @staticmethod
    def of(errors: F64) -> ErrorStatistics:
        e = np.asarray(errors, dtype=np.float64)
        if e.ndim != 1 or len(e) == 0:
            raise ValueError(f"need a non-empty (K,) error vector, got shape {e.shape}")
        sq = np.power(e, 2)
        return ErrorStatistics(
            rmse=math.sqrt(float(np.mean(sq))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            sse=float(np.sum(sq)),
        )

    def as_dict(self) -> dict[str, float]:
        """{'rmse': ..., ..., 'sse': ...}: the keys of evo's `get_all_statistics()`."""
        return {
            "rmse": self.rmse,
            "mean": self.mean,
            "median": self.median,
            "std": self.std,
            "min": self.min,
            "max": self.max,
            "sse": self.sse,
        }


def _stat_fields(errors: F64) -> dict[str, float]:
    return ErrorStatistics.of(errors).as_dict()


# -- helpers --------------------------------------------------------------------------------


def path_length_m(p: F64) -> float:
    """Length of the polyline p (N, 3): sum_k |p_k - p_{k-1}| (evo `geometry.arc_len`);
    0 for fewer than two points."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(p[:-1] - p[1:], axis=1)))


def accumulated_distances_m(p: F64) -> F64:
    """(N,) path distance from p_0 to p_k along the polyline p (N, 3): d_0 = 0,
    d_k = d_{k-1} + |p_k - p_{k-1}| (evo `geometry.accumulated_distances`)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0)
    return np.concatenate((np.zeros(1), np.cumsum(np.linalg.norm(p[:-1] - p[1:], axis=1))))


def _alignment(ref_p: F64, est_p: F64, align: AlignKind) -> Alignment:
    """Umeyama est -> ref; ValueError, as evo, when the cross-covariance has fewer than two
    singular values above machine epsilon (collinear points: the rotation is undetermined)."""
    if align == "none":
        return IDENTITY
    if align not in ("se3", "sim3"):
        raise ValueError(f"align must be 'none', 'se3' or 'sim3', got {align!r}")
    if len(est_p) >= 3:
        cov = (ref_p - ref_p.mean(axis=0)).T @ (est_p - est_p.mean(axis=0)) / len(est_p)
        if np.count_nonzero(np.linalg.svd(cov, compute_uv=False) > np.finfo(float).eps) < 2:
            raise ValueError(
                f"{align} alignment is not possible: the {len(est_p)} matched positions are "
                "degenerate (collinear or coincident)"
            )
    return umeyama(est_p, ref_p, align)


@dataclass(frozen=True, eq=False)
class _Matched:
    ref_idx: I64
    est_idx: I64
    ref_p: F64
    est_p: F64
    alignment: Alignment


def _matched(ref: PoseTable, est: PoseTable, align: AlignKind, max_diff_ns: int) -> _Matched:
    ref_idx, est_idx = associate(ref, est, max_diff_ns)
    ref_p = np.asarray(ref.p_nav_m, dtype=np.float64)[ref_idx]
    est_p = np.asarray(est.p_nav_m, dtype=np.float64)[est_idx]
    alignment = _alignment(ref_p, est_p, align)
    return _Matched(ref_idx, est_idx, ref_p, alignment.apply(est_p), alignment)


# -- APE ------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AteResult(ErrorStatistics):
    """APE translation part. errors_m (K,) = |A(p_est_k) - p_ref_k|; stamps_ns (K,) the
    estimate's stamps of the matched pairs (evo's result 'timestamps'); ref_idx, est_idx (K,)
    the matched rows of the two tables; alignment A (identity for align='none')."""

    errors_m: F64
    stamps_ns: I64
    ref_idx: I64
    est_idx: I64
    alignment: Alignment


def ate(
    ref: PoseTable,
    est: PoseTable,
    align: AlignKind = "none",
    *,
    max_diff_ns: int = DEFAULT_MAX_DIFF_NS,
) -> AteResult:
    """Absolute trajectory error of the positions, as `evo_ape -r trans_part` (align='se3':
    `--align`, 'sim3': `--align --correct_scale`): associate, align the matched estimate
    positions onto the reference (Umeyama over all matched pairs), e_k = |A(p_est_k) - p_ref_k|."""
    m = _matched(ref, est, align, max_diff_ns)
    errors = np.linalg.norm(m.est_p - m.ref_p, axis=1)
    return AteResult(
        **_stat_fields(errors),
        errors_m=errors,
        stamps_ns=np.asarray(est.stamps_ns, dtype=np.int64)[m.est_idx],
        ref_idx=m.ref_idx,
        est_idx=m.est_idx,
        alignment=m.alignment,
    )


# -- RPE ------------------------------------------------------------------------------------


class NoPairsError(ValueError):
    """The RPE delta selects no pose pair (evo's FilterException 'empty index list')."""


def _step_norms(p: F64) -> list[float]:
    # evo's consecutive path filter: float(np.linalg.norm(p_k - p_{k-1})) one vector at a time
    return [float(np.linalg.norm(v)) for v in np.diff(p, axis=0)]


def pairs_by_index(n: int, delta: int, all_pairs: bool = False) -> I64:
    """(P, 2) index pairs (i, i + delta) among n poses: every i (all_pairs) or i = 0, delta,
    2 delta, ... (evo `filters.filter_pairs_by_index`)."""
    if delta < 1:
        raise ValueError(f"delta in frames must be >= 1, got {delta}")
    ids = np.arange(n, dtype=np.int64) if all_pairs else np.arange(0, n, delta, dtype=np.int64)
    if all_pairs:
        ids = ids[ids + delta < n]
        return np.stack([ids, ids + delta], axis=1)
    return np.stack([ids[:-1], ids[1:]], axis=1).reshape(-1, 2)


def pairs_by_path(p: F64, delta_m: float, tol_m: float = 0.0, all_pairs: bool = False) -> I64:
    """(P, 2) index pairs of the positions p (N, 3) separated by delta_m of path (evo
    `filters.filter_pairs_by_path`, see the module docstring; tol_m only with all_pairs)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    if n == 0:
        return np.empty((0, 2), dtype=np.int64)
    if not all_pairs:
        ids = [0]
        current = 0.0
        for k, step in enumerate(_step_norms(p), start=1):
            current += step
            if current >= delta_m:
                ids.append(k)
                current = 0.0
        return np.array(list(itertools.pairwise(ids)), dtype=np.int64).reshape(-1, 2)
    d = accumulated_distances_m(p)
    # evo scans every row i with argmin |(d[i+1:] - d[i]) - delta|. d[k] - d[i] is
    # non-decreasing in k, so the first minimum sits where it crosses delta: search a small
    # window around d[i] + delta (margin far above rounding), then evaluate evo's exact
    # expression there, stepping back over equal values to keep argmin's first index.
    margin = 1e-6 * (abs(float(d[-1])) + abs(delta_m)) + 1e-9
    lo_all = np.searchsorted(d, d[:-1] + delta_m - margin, side="left") - 1
    hi_all = np.searchsorted(d, d[:-1] + delta_m + margin, side="right")
    out = []
    for i in range(n - 1):
        lo = max(i + 1, int(lo_all[i]))
        hi = min(n - 1, int(hi_all[i]))
        dist = d[lo : hi + 1] - d[i]
        k = int(np.argmin(np.abs(dist - delta_m)))
        j, value = lo + k, float(dist[k])
        while k == 0 and j - 1 > i and float(d[j - 1] - d[i]) == value:
            j -= 1
        if abs(value - delta_m) > tol_m:
            continue
        out.append((i, j))
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def _se3(p: F64, q_xyzw: F64, alignment: Alignment = IDENTITY) -> F64:
    """(K, 4, 4) poses [R_a R(q) | s R_a p + t_a]."""
    T = np.zeros((len(p), 4, 4))
    T[:, :3, :3] = alignment.R @ quat_xyzw_to_matrix(np.asarray(q_xyzw, dtype=np.float64))
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T


def _relative(Ti: F64, Tj: F64) -> F64:
    """Ti^-1 Tj with Ti^-1 = [R^T | -R^T t] (evo `lie.relative_se3`), batched (P, 4, 4)."""
    inv = np.zeros_like(Ti)
    Rt = np.swapaxes(Ti[:, :3, :3], 1, 2)
    inv[:, :3, :3] = Rt
    inv[:, :3, 3] = -np.einsum("kab,kb->ka", Rt, Ti[:, :3, 3])
    inv[:, 3, 3] = 1.0
    return inv @ Tj


@dataclass(frozen=True, eq=False)
class RpeResult(ErrorStatistics):
    """RPE translation part. errors_m (P,) = |trans(E_ij)| per pair; pairs (P, 2) the (i, j)
    indices into the matched sequence (ref_idx, est_idx (K,) map them to table rows);
    stamps_ns (P,) the estimate's stamp of each pair's second pose j (evo's 'timestamps');
    delta, unit as asked; alignment applied to the estimate before the pairs are chosen."""

    errors_m: F64
    pairs: I64
    stamps_ns: I64
    ref_idx: I64
    est_idx: I64
    delta: float
    unit: DeltaUnit
    alignment: Alignment


def rpe(
    ref: PoseTable,
    est: PoseTable,
    delta: float,
    unit: DeltaUnit = "frames",
    all_pairs: bool = False,
    align: AlignKind = "none",
    *,
    pairs_from_reference: bool = False,
    rel_delta_tol: float = 0.1,
    max_diff_ns: int = DEFAULT_MAX_DIFF_NS,
) -> RpeResult:
    """Relative pose error, translation part, as `evo_rpe -r trans_part --delta D
    --delta_unit m|f [--all_pairs] [--align [--correct_scale]] [--pairs_from_reference]`
    (module docstring: E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j), pairs chosen on the aligned
    estimate unless pairs_from_reference). `NoPairsError` (a ValueError) when no pair
    qualifies (evo FilterException); ValueError for a negative delta or a non-integer delta
    in frames."""
    if unit not in ("m", "frames"):
        raise ValueError(f"unit must be 'm' or 'frames', got {unit!r}")
    if not delta >= 0:
        raise ValueError(f"delta must be >= 0, got {delta}")
    if unit == "frames" and float(delta) != int(delta):
        raise ValueError(f"delta must be an integer number of frames, got {delta}")
    m = _matched(ref, est, align, max_diff_ns)
    Q = _se3(m.ref_p, np.asarray(ref.q_nav_body_xyzw)[m.ref_idx])
    P = _se3(m.est_p, np.asarray(est.q_nav_body_xyzw)[m.est_idx], m.alignment)
    source = m.ref_p if pairs_from_reference else m.est_p
    if unit == "frames":
        pairs = pairs_by_index(len(source), int(delta), all_pairs)
    else:
        pairs = pairs_by_path(source, float(delta), float(delta) * rel_delta_tol, all_pairs)
    if len(pairs) == 0:
        raise NoPairsError(
            f"delta = {delta} ({unit}) produced no pose pair among {len(source)} matched "
            "poses - try a lower value or a less strict tolerance"
        )
    i, j = pairs[:, 0], pairs[:, 1]
    E = _relative(_relative(Q[i], Q[j]), _relative(P[i], P[j]))
    errors = np.linalg.norm(E[:, :3, 3], axis=1)
    return RpeResult(
        **_stat_fields(errors),
        errors_m=errors,
        pairs=pairs,
        stamps_ns=np.asarray(est.stamps_ns, dtype=np.int64)[m.est_idx[j]],
        ref_idx=m.ref_idx,
        est_idx=m.est_idx,
        delta=float(delta),
        unit=unit,
        alignment=m.alignment,
    )


# -- drift per distance ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class DistanceDrift:
    """RPE at one pair distance delta_m. drift_pct (P,) = 100 e_ij / s_ij with e_ij the RPE
    translation error and s_ij = d_ref[j] - d_ref[i] the reference's path length between the
    pair's poses; mean_pct = mean(drift_pct), rmse_pct = sqrt(mean(drift_pct^2)).
    n_pairs = 0 (and NaN figures, rpe None) when no pair of this length exists."""

    delta_m: float
    n_pairs: int
    mean_pct: float
    rmse_pct: float
    drift_pct: F64
    rpe: RpeResult | None


@dataclass(frozen=True, eq=False)
class DriftSummary:
    """KITTI-style translational drift. rows: one `DistanceDrift` per delta; average_pct:
    the mean of drift_pct over the pairs of all deltas pooled (the KITTI devkit's t_err,
    in %), NaN when no delta gave a pair."""

    rows: tuple[DistanceDrift, ...]
    average_pct: float


def rpe_per_distance(
    ref: PoseTable,
    est: PoseTable,
    deltas_m: Sequence[float] | None = None,
    *,
    fractions: Sequence[float] | None = None,
    align: AlignKind = "none",
    all_pairs: bool = True,
    pairs_from_reference: bool = True,
    rel_delta_tol: float = 0.1,
    max_diff_ns: int = DEFAULT_MAX_DIFF_NS,
) -> DriftSummary:
    """Translational drift in % of distance travelled, for several pair distances (KITTI
    odometry style): give `deltas_m` (e.g. (10, 50, 100)) or `fractions` of the reference's
    path length over the matched poses (delta = f * L_ref). For each delta, `rpe(..., delta,
    'm', all_pairs, align, pairs_from_reference=..., rel_delta_tol=...)` (defaults: all pairs
    chosen on the reference's path, kept within +-10 % of delta, like the devkit's
    sub-sequences started at every frame), then per pair 100 |trans(E_ij)| / s_ij, s_ij the
    reference path length between the two poses (see `DistanceDrift`, `DriftSummary`)."""
    if (deltas_m is None) == (fractions is None):
        raise ValueError("give exactly one of deltas_m and fractions")
    ref_idx, _ = associate(ref, est, max_diff_ns)
    d_ref = accumulated_distances_m(np.asarray(ref.p_nav_m, dtype=np.float64)[ref_idx])
    if fractions is not None:
        deltas = [float(f) * float(d_ref[-1]) for f in fractions]
    else:
        deltas = [float(x) for x in deltas_m or ()]
    rows = []
    pooled = []
    for delta in deltas:
        if not delta > 0:
            raise ValueError(f"pair distances must be > 0 m, got {delta}")
        try:
            res = rpe(
                ref,
                est,
                delta,
                "m",
                all_pairs,
                align,
                pairs_from_reference=pairs_from_reference,
                rel_delta_tol=rel_delta_tol,
                max_diff_ns=max_diff_ns,
            )
        except NoPairsError:
            rows.append(DistanceDrift(delta, 0, math.nan, math.nan, np.zeros(0), None))
            continue
        s = d_ref[res.pairs[:, 1]] - d_ref[res.pairs[:, 0]]
        with np.errstate(divide="ignore", invalid="ignore"):
            pct = np.where(s > 0, 100.0 * res.errors_m / np.where(s > 0, s, 1.0), np.nan)
        pct = pct[np.isfinite(pct)]
        pooled.append(pct)
        rows.append(
            DistanceDrift(
                delta_m=delta,
                n_pairs=len(pct),
                mean_pct=float(np.mean(pct)) if len(pct) else math.nan,
                rmse_pct=math.sqrt(float(np.mean(pct**2))) if len(pct) else math.nan,
                drift_pct=pct,
                rpe=res,
            )
        )
    allpct = np.concatenate(pooled) if pooled else np.zeros(0)
    return DriftSummary(tuple(rows), float(np.mean(allpct)) if len(allpct) else math.nan)


# -- final drift ----------------------------------------------------------------------------


def final_drift(
    ref: PoseTable,
    est: PoseTable,
    align: AlignKind = "none",
    *,
    max_diff_ns: int = DEFAULT_MAX_DIFF_NS,
) -> tuple[float, float]:
    """(metres, percent) drift at the end: |A(p_est) - p_ref| at the last matched pair, and
    100 x that / L, L the reference's path length over all its poses from the first to the
    last matched one (`path_length_m`). Percent is NaN when L = 0."""
    m = _matched(ref, est, align, max_diff_ns)
    drift = float(np.linalg.norm(m.est_p[-1] - m.ref_p[-1]))
    a, b = int(m.ref_idx[0]), int(m.ref_idx[-1])
    length = path_length_m(np.asarray(ref.p_nav_m, dtype=np.float64)[min(a, b) : max(a, b) + 1])
    return drift, (100.0 * drift / length if length > 0 else math.nan)


# -- consistency ----------------------------------------------------------------------------


def nees_position(ref_p: F64, est_p: F64, cov_p: F64) -> F64:
    """(K,) normalised estimation error squared of the position:
    eps_k = e_k^T P_k^-1 e_k, e_k = est_p_k - ref_p_k (K, d), P_k = cov_p[k] (K, d, d) the
    estimate's position covariance (m^2); d = 3, or 2 for the horizontal position of a ground
    robot. A consistent filter has E[eps_k] = d (chi2, d dof)."""
    ref_p = np.asarray(ref_p, dtype=np.float64)
    est_p = np.asarray(est_p, dtype=np.float64)
    cov_p = np.asarray(cov_p, dtype=np.float64)
    if ref_p.shape != est_p.shape or ref_p.ndim != 2 or not 1 <= ref_p.shape[1] <= 3:
        raise ValueError(f"need two (K, d <= 3) arrays, got {ref_p.shape} and {est_p.shape}")
    d = ref_p.shape[1]
    if cov_p.shape != (len(ref_p), d, d):
        raise ValueError(f"need cov_p of shape ({len(ref_p)}, {d}, {d}), got {cov_p.shape}")
    e = est_p - ref_p
    return np.einsum("ka,ka->k", e, np.linalg.solve(cov_p, e[:, :, None])[:, :, 0])


def nees_chi2_band(dof: int = 3, n_runs: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided acceptance band (lo, hi) of the NEES averaged over n_runs independent runs
    (Bar-Shalom): n_runs * mean_eps ~ chi2(n_runs * dof), so
    lo = chi2.ppf((1 - c) / 2, n dof) / n,  hi = chi2.ppf((1 + c) / 2, n dof) / n."""
    if dof < 1 or n_runs < 1 or not 0.0 < confidence < 1.0:
        raise ValueError(
            f"need dof >= 1, n_runs >= 1 and 0 < confidence < 1, got {dof}, {n_runs}, {confidence}"
        )
    k = dof * n_runs
    lo = float(chi2.ppf((1.0 - confidence) / 2.0, k)) / n_runs
    hi = float(chi2.ppf((1.0 + confidence) / 2.0, k)) / n_runs
    return lo, hi
