"""The refined run's map file: the source fuse run's `LandmarkArchive` (`map.npz`) with the
refined landmarks moved to their batch solution and given its marginal covariances, and the
new points of re-association's tracks added, so that a refined run can be the prior map of a
later one (`cvslam fuse RUN --prior-map RUN/fuse_refined`, docs/refine.md).

For a new point the archive's fields come from its observations in the problem: observers
and times, the observation count, and its mean viewing direction from the observing
keyframes' body positions (the cameras are centimetres from them; the direction only
decides from where a landmark is expected in view). Its descriptor is the one
re-association matched it with. A new point is out of any filter state (`in_state` false),
never evicted nor re-activated, and of the source's latest mapping session. The refined
landmarks and the new points are marked `batch` (`LandmarkArchive.batch`): a later run
takes them with `fuse.map.refined_prior_map_inflation`, and the source's landmarks the
batch did not solve (seen from fewer than two keyframes) with the filter's inflation
(`estimation/prior_map.py`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import F64, I64, U8
from cvslam_cli.records.landmark_archive import NEVER_NS, LandmarkArchive
from cvslam_cli.refine.problem import RefineProblem, RefineResult


def refined_archive(
    source: LandmarkArchive,
    problem: RefineProblem,
    res: RefineResult,
    descriptor: U8 | None = None,
    true_id: I64 | None = None,
) -> LandmarkArchive:
    """`source` with the problem's landmarks refined (position; covariance where `res` has
    one) and the problem's landmarks not in it appended (module docstring), with
    `descriptor` (L, D) and `true_id` (L,) per problem landmark (needed for new ones)."""
    row_of = {int(i): r for r, i in enumerate(source.landmark_id)}
    rows = np.array([row_of.get(int(i), -1) for i in problem.landmark_id], dtype=np.int64)
    known = rows >= 0
    p = source.p_nav_m.copy()
    cov = source.cov_nav_m2.copy()
    # a refined landmark is the batch solution's, its covariance too (NaN: not computed,
    # `refine.landmark_covariances`, as map.csv says; a prior map then leaves it out)
    p[rows[known]] = res.p_nav_m[known]
    cov[rows[known]] = res.cov[known]
    batch = np.array(source.batch, copy=True)
    batch[rows[known]] = True
    new = np.flatnonzero(~known)
    if len(new) and descriptor is None:
        raise ValueError("refined_archive: new points need their descriptors")
    new_desc = source.descriptor[:0] if descriptor is None else descriptor[new]
    names = [v.name for v in problem.vehicles]
    vehicles = list(source.vehicles) + [n for n in names if n not in source.vehicles]
    last = np.full((len(source) + len(new), len(vehicles)), NEVER_NS, dtype=np.int64)
    last[: len(source), : len(source.vehicles)] = source.last_seen_ns
    obs = observed(problem, new, res.p_nav_m[new])
    last[len(source) :, [vehicles.index(n) for n in names]] = obs.last_ns
    tid = np.full(len(new), -1, dtype=np.int64) if true_id is None else true_id[new]
    sessions = source.session if source.session is not None else np.zeros(len(source), np.int64)
    session = int(sessions.max()) if len(source) else 0
    return LandmarkArchive(
        vehicles=tuple(vehicles),
        landmark_id=np.concatenate([source.landmark_id, problem.landmark_id[new]]),
        true_id=np.concatenate([source.true_id, tid]),
        p_nav_m=np.vstack([p, res.p_nav_m[new]]),
        cov_nav_m2=np.concatenate([cov, res.cov[new]]),
        descriptor=np.vstack([source.descriptor, new_desc]),
        view_dir_sum_nav=np.vstack([source.view_dir_sum_nav, obs.view]),
        first_seen_ns=np.concatenate([source.first_seen_ns, obs.first_ns]),
        last_seen_ns=last,
        n_observations=np.concatenate([source.n_observations, obs.count]),
        in_state=np.concatenate([source.in_state, np.zeros(len(new), dtype=bool)]),
        evicted_ns=np.concatenate([source.evicted_ns, np.full(len(new), NEVER_NS)]),
        reactivations=np.concatenate([source.reactivations, np.zeros(len(new), dtype=np.int64)]),
        session=np.concatenate([sessions, np.full(len(new), session, dtype=np.int64)]),
        batch=np.concatenate([batch, np.ones(len(new), dtype=bool)]),
        coordinates=source.coordinates,
    )


@dataclass(frozen=True, eq=False)
class Observed:
    """What the problem's observations say of k of its landmarks: `view` (k, 3) the sum of
    unit vectors to the observing keyframes' positions, `first_ns` (k,) the first stamp,
    `count` (k,) the observations, `last_ns` (k, V) each problem vehicle's last stamp
    (`NEVER_NS`: not observed by it)."""

    view: F64
    first_ns: I64
    count: I64
    last_ns: I64

    def observers(self, names: Sequence[str]) -> list[str]:
        """Per landmark the observing vehicles (`names`: the problem's), sorted, ";"-joined
        (map.csv's column)."""
        seen = self.last_ns != NEVER_NS
        return [";".join(sorted(n for n, s in zip(names, row, strict=True) if s)) for row in seen]


def observed(problem: RefineProblem, landmarks: I64, p_nav_m: F64) -> Observed:
    """`Observed` for the problem's `landmarks` (k,) at `p_nav_m` (k, 3)."""
    n = len(landmarks)
    view = np.zeros((n, 3))
    count = np.zeros(n, dtype=np.int64)
    first = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
    last = np.full((n, len(problem.vehicles)), NEVER_NS, dtype=np.int64)
    offset = np.cumsum([0] + [len(v.stamps_ns) for v in problem.vehicles])[:-1]
    stamps = np.concatenate([v.stamps_ns for v in problem.vehicles])
    where = np.concatenate([v.T_nav_body[:, :3, 3] for v in problem.vehicles])
    at = np.full(len(problem.landmark_id), -1, dtype=np.int64)
    at[landmarks] = np.arange(n)
    k = at[problem.obs_landmark]
    sel = k >= 0
    k = k[sel]
    kf = offset[problem.obs_vehicle[sel]] + problem.obs_keyframe[sel]
    t = stamps[kf]
    d = where[kf] - p_nav_m[k]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    np.add.at(view, k, d)
    np.add.at(count, k, 1)
    np.minimum.at(first, k, t)
    np.maximum.at(last, (k, problem.obs_vehicle[sel]), t)
    return Observed(view, first, count, last)
