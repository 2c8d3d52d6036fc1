"""Re-association: more of what the images hold for the batch (pure numpy; docs/refine.md).

The filter associates a bounded number of landmarks per frame (`fuse.map.
max_updates_per_frame`), none that its bounded state evicted, and maps a few new points a
frame; the features file holds every stereo match of every frame. One round of
re-association, from the current estimate of the keyframe poses and the points:

1. the filter's own observations are kept (after a solution: only those inside the
   chi-square gate, `radius`);
2. every point (the map's landmarks, the tracks of earlier rounds) is predicted into every
   keyframe of every vehicle that has not observed it there and guided-matched with the
   keyframe's unclaimed stereo matches (`guided_matching.py`): loop closures and
   re-observations the filter missed or could not afford, across vehicles too;
3. the matches still unclaimed are tracked across consecutive keyframes
   (`feature_tracks.py`); a track seen in `min_track_keyframes` keyframes is a new point.

A point's descriptors are the features it was observed with (at most `max_descriptors`,
spread along its observations); a map landmark starts with the ones of the filter's
observations (found again in the features file by their pixels) and the archive's.
`problem_of` turns the round's observations into a `RefineProblem` (points seen from two
keyframes or more); after solving, `update_points` carries the solution into the next round.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, U8, BoolArray, check_shape
from cvslam_cli.refine.feature_tracks import track_free_features
from cvslam_cli.refine.guided_matching import in_images, match, project
from cvslam_cli.refine.keyframe_features import KeyframeFeatures
from cvslam_cli.refine.problem import RefineProblem, RefineVehicle

NEW_POINT = -1
"""`Points.landmark_id` of a point from a feature track (no map id yet)."""


@dataclass(frozen=True)
class ReassociationSettings:
    """rounds: associate-and-solve rounds (0: the filter's observations only); gate_px: the
    pixel gate (over the 4 coordinates) of the first round, around predictions from the
    filter's estimate; gate_probability: the chi-square gate (4 dof) of later rounds and of
    the final check, in units of the residual scale at the solution; the descriptor ratio
    test and largest distance; tracks: also track the unclaimed stereo matches into new
    points seen in at least min_track_keyframes keyframes; max_descriptors per point."""

    rounds: int = 2
    gate_px: float = 4.0
    gate_probability: float = 0.999
    descriptor_ratio: float = 0.8
    max_descriptor_distance: float = 350.0
    tracks: bool = True
    min_track_keyframes: int = 3
    max_descriptors: int = 8


@dataclass(frozen=True, eq=False)
class Points:
    """L points: landmark_id (L,) the map's id (`NEW_POINT` for a track's), p_nav_m (L, 3)
    current positions, desc (L, S, D) uint8 descriptor sets with n_desc (L,) >= 1 valid rows
    each, true_id (L,) the simulator's id (-1 unknown)."""

    landmark_id: I64
    p_nav_m: F64
    desc: U8
    n_desc: I64
    true_id: I64

    def __post_init__(self) -> None:
        dims: dict[str, int] = {}
        check_shape("Points.landmark_id", self.landmark_id, ("L",), "i", dims)
        check_shape("Points.p_nav_m", self.p_nav_m, ("L", 3), "f", dims)
        check_shape("Points.desc", self.desc, ("L", "S", "D"), "u", dims)
        check_shape("Points.n_desc", self.n_desc, ("L",), "iu", dims)
        check_shape("Points.true_id", self.true_id, ("L",), "i", dims)

    def __len__(self) -> int:
        return len(self.landmark_id)


@dataclass(frozen=True, eq=False)
class Observed:
    """N observations: vehicle (N,), keyframe (N,), point (N,) a row of `Points`, feature
    (N,) the row in the vehicle's `KeyframeFeatures` (-1: none found), z_px (N, 4), base (N,)
    True for the filter's own."""

    vehicle: I64
    keyframe: I64
    point: I64
    feature: I64
    z_px: F64
    base: BoolArray

    def __len__(self) -> int:
        return len(self.point)

    def take(self, rows: I64 | BoolArray) -> Observed:
        return Observed(
            self.vehicle[rows], self.keyframe[rows], self.point[rows], self.feature[rows],
            self.z_px[rows], self.base[rows],
        )  # fmt: skip

    @staticmethod
    def concatenate(parts: Sequence[Observed]) -> Observed:
        def cat(name: str) -> np.ndarray:
            return np.concatenate([getattr(p, name) for p in parts])

        return Observed(
            *(cat(n) for n in ("vehicle", "keyframe", "point", "feature", "z_px", "base"))
        )


def _empty_observed() -> Observed:
    e = np.zeros(0, dtype=np.int64)
    return Observed(e, e, e, e, np.zeros((0, 4)), np.zeros(0, dtype=bool))


def descriptor_sets(
    n_points: int, point: I64, desc: U8, max_descriptors: int, start: U8 | None = None
) -> tuple[U8, I64]:
    """((L, S, D), n_desc (L,)): each point's descriptors desc[i] (n, D) of its observations
    point (n,) (in the given order; at most max_descriptors, evenly spread over them),
    after `start` (L, D) when given (the archive's descriptor). n_desc 0: none."""
    D = desc.shape[1] if desc.ndim == 2 and desc.shape[1] else 128
    S = max_descriptors
    out = np.zeros((n_points, S, D), dtype=np.uint8)
    n = np.zeros(n_points, dtype=np.int64)
    offset = 0
    if start is not None:
        out[:, 0] = start
        n[:] = 1
        offset = 1
    order = np.argsort(point, kind="stable")
    p_sorted = point[order]
    first = np.searchsorted(p_sorted, np.arange(n_points), side="left")
    last = np.searchsorted(p_sorted, np.arange(n_points), side="right")
    room = S - offset
    for j in np.flatnonzero(last > first):
        rows = order[first[j] : last[j]]
        if len(rows) > room:
            rows = rows[np.linspace(0, len(rows) - 1, room).round().astype(int)]
        out[j, offset : offset + len(rows)] = desc[rows]
        n[j] = offset + len(rows)
    return out, n


def predicted_d2(
    vehicles: Sequence[RefineVehicle], poses: Sequence[F64], points: Points, obs: Observed
) -> F64:
    """(N,) squared pixel distance of each observation from its prediction (4 coordinates)."""
    out = np.full(len(obs), np.inf)
    for v, veh in enumerate(vehicles):
        for k in np.unique(obs.keyframe[obs.vehicle == v]):
            sel = np.flatnonzero((obs.vehicle == v) & (obs.keyframe == k))
            z, depth = project(
                poses[v][k], veh.K_px, veh.T_body_cam, points.p_nav_m[obs.point[sel]]
            )
            ok = np.all(depth > 0, axis=1)
            out[sel[ok]] = np.sum((z[ok] - obs.z_px[sel[ok]]) ** 2, axis=1)
    return out


def associate(
    vehicles: Sequence[RefineVehicle],
    poses: Sequence[F64],
    features: Sequence[KeyframeFeatures],
    points: Points,
    base: Observed,
    radius_px: float,
    check_base: bool,
    settings: ReassociationSettings,
) -> tuple[Points, Observed]:
    """One round (module docstring): (points with the new tracks appended, observations).
    `poses[v]` (K_v, 4, 4) the current keyframe poses, `points.p_nav_m` the current
    positions; `radius_px` the gate; `check_base`: gate the filter's observations too."""
    if check_base and len(base):
        base = base.take(predicted_d2(vehicles, poses, points, base) < radius_px**2)
    parts = [base]
    new_points: list[Points] = []
    n_points = len(points)
    for v, (veh, kf) in enumerate(zip(vehicles, features, strict=True)):
        M = len(kf.z_px)
        claimed = np.zeros(M, dtype=bool)
        mine = base.vehicle == v
        claimed[base.feature[mine & (base.feature >= 0)]] = True
        L = max(len(points), 1)
        seen_at = np.unique(base.keyframe[mine] * L + base.point[mine])
        found_k, found_p, found_f = [], [], []
        for k in range(kf.n_keyframes):
            rows = np.arange(*kf.rows(k).indices(M))
            rows = rows[~claimed[rows]]
            if not len(rows) or not len(points):
                continue
            z, depth = project(poses[v][k], veh.K_px, veh.T_body_cam, points.p_nav_m)
            cand = np.flatnonzero(in_images(z, depth, kf.size_px))
            cand = cand[~np.isin(k * L + cand, seen_at)]
            if not len(cand):
                continue
            m = match(
                z[cand], points.desc[cand], points.n_desc[cand], kf.z_px[rows], kf.desc[rows],
                radius_px, settings.descriptor_ratio, settings.max_descriptor_distance,
            )  # fmt: skip
            claimed[rows[m.feature]] = True
            found_k.append(np.full(len(m), k, dtype=np.int64))
            found_p.append(cand[m.point])
            found_f.append(rows[m.feature])
        if found_f:
            f = np.concatenate(found_f)
            parts.append(
                Observed(
                    np.full(len(f), v, dtype=np.int64), np.concatenate(found_k),
                    np.concatenate(found_p), f, kf.z_px[f], np.zeros(len(f), dtype=bool),
                )
            )  # fmt: skip
        if not settings.tracks:
            continue
        tr = track_free_features(
            poses[v], veh.K_px, veh.T_body_cam, kf, ~claimed, radius_px,
            settings.descriptor_ratio, settings.max_descriptor_distance,
            settings.min_track_keyframes,
        )  # fmt: skip
        if not len(tr):
            continue
        desc, n_desc = descriptor_sets(
            len(tr), tr.track, kf.desc[tr.feature], settings.max_descriptors
        )
        new_points.append(
            Points(
                np.full(len(tr), NEW_POINT, dtype=np.int64), tr.p_nav_m, desc, n_desc,
                _track_true_ids(len(tr), tr.track, kf.true_id[tr.feature]),
            )
        )  # fmt: skip
        parts.append(
            Observed(
                np.full(len(tr.feature), v, dtype=np.int64), kf.keyframe_of(tr.feature),
                n_points + tr.track, tr.feature, kf.z_px[tr.feature],
                np.zeros(len(tr.feature), dtype=bool),
            )
        )  # fmt: skip
        n_points += len(tr)
    if new_points:
        points = Points(
            *(np.concatenate([getattr(p, n) for p in (points, *new_points)])
              for n in ("landmark_id", "p_nav_m", "desc", "n_desc", "true_id"))
        )  # fmt: skip
    return points, Observed.concatenate(parts) if len(parts) > 1 else base


def _track_true_ids(n: int, track: I64, true_id: I64) -> I64:
    """(n,) the most frequent simulator id along each track (-1 unknown)."""
    out = np.full(n, -1, dtype=np.int64)
    for t in range(n):
        ids, counts = np.unique(true_id[track == t], return_counts=True)
        out[t] = ids[np.argmax(counts)]
    return out


@dataclass(frozen=True, eq=False)
class ProblemRows:
    """How a `RefineProblem` maps back: `points` (L',) the `Points` row of each of its
    landmarks, `observed` (N',) the `Observed` row of each of its observations."""

    points: I64
    observed: I64


def problem_of(
    vehicles: Sequence[RefineVehicle],
    poses: Sequence[F64],
    points: Points,
    obs: Observed,
    next_id: int,
) -> tuple[RefineProblem, ProblemRows]:
    """The problem over the points seen from two keyframes or more (one observation per
    (vehicle, keyframe, point)), initialised at `poses` and the points' positions; a new
    point takes the id next_id + its rank among the new points kept."""
    key = np.stack([obs.vehicle, obs.keyframe, obs.point], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    rows = np.sort(first)
    ids, counts = np.unique(obs.point[rows], return_counts=True)
    good = ids[counts >= 2]
    rows = rows[np.isin(obs.point[rows], good)]
    landmark_id = points.landmark_id[good].copy()
    new = landmark_id == NEW_POINT
    landmark_id[new] = next_id + np.arange(int(new.sum()))
    veh = tuple(dataclasses.replace(v, T_nav_body=poses[i]) for i, v in enumerate(vehicles))
    problem = RefineProblem(
        veh, obs.vehicle[rows], obs.keyframe[rows],
        np.searchsorted(good, obs.point[rows]).astype(np.int64), obs.z_px[rows],
        landmark_id, points.p_nav_m[good],
    )  # fmt: skip
    return problem, ProblemRows(good, rows)


def update_points(
    points: Points,
    rows: ProblemRows,
    p_nav_m: F64,
    obs: Observed,
    features: Sequence[KeyframeFeatures],
    max_descriptors: int,
) -> Points:
    """The points for the next round: the solved ones at `p_nav_m` (L', 3) (problem order),
    their descriptor sets from the features they were observed with; the map's landmarks
    kept (unsolved ones where they were), the tracks' points not solved dropped."""
    p = points.p_nav_m.copy()
    p[rows.points] = p_nav_m
    used = obs.take(rows.observed)
    used = used.take(used.feature >= 0)
    desc = np.zeros((len(used), points.desc.shape[2]), dtype=np.uint8)
    for v, kf in enumerate(features):
        sel = used.vehicle == v
        desc[sel] = kf.desc[used.feature[sel]]
    sets, n = descriptor_sets(len(points), used.point, desc, max_descriptors)
    keep_old = n == 0
    sets[keep_old] = points.desc[keep_old]
    n[keep_old] = points.n_desc[keep_old]
    solved = np.zeros(len(points), dtype=bool)
    solved[rows.points] = True
    keep = solved | (points.landmark_id != NEW_POINT)
    return Points(points.landmark_id[keep], p[keep], sets[keep], n[keep], points.true_id[keep])
