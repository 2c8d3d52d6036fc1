"""Keyframe selection: which of a vehicle's frames become pose variables, and which
observations and landmarks the graph keeps. Bounded memory: every `every_nth` frame (and the
last) of each vehicle, and only the landmarks seen from at least two keyframes (a landmark
seen from one pose has as many unknowns as it constrains: it cannot correct the pose)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cvslam_cli.records.arrays import I64


def select_keyframes(n_frames: int, every_nth: int) -> I64:
    """Indices (K,) of the kept frames among n_frames: every `every_nth`, and the last."""
    if every_nth < 1:
        raise ValueError(f"every_nth: expected an integer >= 1, got {every_nth}")
    if n_frames == 0:
        return np.zeros(0, dtype=np.int64)
    keep = np.arange(0, n_frames, every_nth, dtype=np.int64)
    return keep if keep[-1] == n_frames - 1 else np.append(keep, n_frames - 1)


@dataclass(frozen=True, eq=False)
class KeptObservations:
    """The observations kept (`rows` (N',) into the input arrays) with their keyframe index
    (N',) in the vehicle's keyframes and landmark index (N',) into `landmark_ids` (L',)."""

    rows: I64
    keyframe: I64
    landmark: I64
    landmark_ids: I64


def keep_observations(
    obs_vehicle: I64,
    obs_stamp_ns: I64,
    obs_landmark_id: I64,
    keyframe_stamps_ns: list[I64],
    min_keyframes: int = 2,
) -> KeptObservations:
    """The observations made at a keyframe (stamp equal to one of its vehicle's
    keyframe_stamps_ns[v], increasing), of landmarks seen from at least `min_keyframes`
    keyframes (counting each (vehicle, keyframe) once)."""
    n = len(obs_stamp_ns)
    kf = np.full(n, -1, dtype=np.int64)
    for v, stamps in enumerate(keyframe_stamps_ns):
        sel = np.flatnonzero(obs_vehicle == v)
        if not len(sel) or not len(stamps):
            continue
        i = np.clip(np.searchsorted(stamps, obs_stamp_ns[sel]), 0, len(stamps) - 1)
        hit = stamps[i] == obs_stamp_ns[sel]
        kf[sel[hit]] = i[hit]
    rows = np.flatnonzero(kf >= 0)
    # one observation per (vehicle, keyframe, landmark): a repeat would count twice
    key = np.stack([obs_vehicle[rows], kf[rows], obs_landmark_id[rows]], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    rows = rows[np.sort(first)]
    ids, counts = np.unique(obs_landmark_id[rows], return_counts=True)
    good = ids[counts >= min_keyframes]
    rows = rows[np.isin(obs_landmark_id[rows], good)]
    return KeptObservations(
        rows, kf[rows], np.searchsorted(good, obs_landmark_id[rows]).astype(np.int64), good
    )
