"""A `RefineProblem` from what the filter had and gave (pure: arrays in, arrays out): its
vehicle inputs (motion model, initial state, motion samples, rig), its estimated
trajectories (the initial poses), the observations it used and its map (the initial
landmark positions)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cvslam_cli.estimation.motion.models import propagate
from cvslam_cli.estimation.motion.segments import motion_segments
from cvslam_cli.estimation.vehicle import VehicleInput
from cvslam_cli.geometry.rotations import make_T, quat_xyzw_to_matrix
from cvslam_cli.records.arrays import F64, I64, U8
from cvslam_cli.records.observations import ObservationTable
from cvslam_cli.records.poses import PoseTable
from cvslam_cli.refine.keyframe_features import KeyframeFeatures, find_rows
from cvslam_cli.refine.keyframes import keep_observations, select_keyframes
from cvslam_cli.refine.problem import RefineProblem, RefineVehicle
from cvslam_cli.refine.reassociation import Observed, Points, descriptor_sets


def _poses(table: PoseTable) -> F64:
    """(N, 4, 4) T_nav_body of a pose table."""
    T = np.tile(np.eye(4), (len(table), 1, 1))
    for i in range(len(table)):
        T[i] = make_T(quat_xyzw_to_matrix(table.q_nav_body_xyzw[i]), table.p_nav_m[i])
    return T


def prior_at(vin: VehicleInput, stamp_ns: int) -> tuple[F64, F64]:
    """The filter's prior (x, P) at `stamp_ns`: its initial state at start_ns predicted
    over the motion samples up to that stamp (what its first frame there starts from)."""
    U, dts = motion_segments(vin.motion_stamps_ns, vin.motion_inputs, vin.start_ns, stamp_ns)
    if not len(dts):
        return vin.x0.copy(), vin.P0.copy()
    x, F, Q = propagate(vin.model, vin.x0, U, dts)
    return x, F @ vin.P0 @ F.T + Q


def build_problem(
    inputs: Sequence[VehicleInput],
    tracks: dict[str, PoseTable],
    observations: ObservationTable,
    landmark_id: I64,
    landmark_p_nav_m: F64,
    every_nth: int = 1,
) -> RefineProblem:
    """The problem over the vehicles of `inputs` that have a track: keyframes every
    `every_nth` frame of each track (`keyframes.py`), the observations made at them of
    landmarks seen from two keyframes or more, initialised at the map's positions
    (`landmark_id` (L,) with `landmark_p_nav_m` (L, 3); every observed id must be there)."""
    vehicles: list[RefineVehicle] = []
    stamps: list[I64] = []
    index_of = {name: i for i, name in enumerate(observations.vehicles)}
    obs_vehicle = np.full(len(observations), -1, dtype=np.int64)
    for vin in inputs:
        table = tracks.get(vin.name)
        if table is None or len(table) == 0:
            continue
        keep = select_keyframes(len(table), every_nth)
        st = table.stamps_ns[keep].astype(np.int64)
        x_first, P_first = prior_at(vin, int(st[0]))
        obs = vin.obs
        T_body_cam = np.stack([make_T(obs.R_cam_body[c].T, obs.t_body_cam[c]) for c in range(2)])
        if vin.name in index_of:
            obs_vehicle[observations.vehicle == index_of[vin.name]] = len(vehicles)
        vehicles.append(
            RefineVehicle(
                vin.name, vin.model, st, _poses(table)[keep], x_first, P_first,
                vin.motion_stamps_ns, vin.motion_inputs, obs.K.astype(float), T_body_cam,
            )
        )  # fmt: skip
        stamps.append(st)
    kept = keep_observations(obs_vehicle, observations.stamp_ns, observations.landmark_id, stamps)
    row_of = {int(i): r for r, i in enumerate(landmark_id)}
    missing = [int(i) for i in kept.landmark_ids if int(i) not in row_of]
    if missing:
        raise ValueError(f"observed landmark ids not in the map: {missing[:5]}")
    found = np.array([row_of[int(i)] for i in kept.landmark_ids], dtype=np.int64)
    return RefineProblem(
        tuple(vehicles),
        obs_vehicle[kept.rows],
        kept.keyframe,
        kept.landmark,
        observations.z_px[kept.rows],
        kept.landmark_ids,
        np.asarray(landmark_p_nav_m, dtype=float)[found].reshape(-1, 3),
    )


def reassociation_start(
    vehicles: Sequence[RefineVehicle],
    features: Sequence[KeyframeFeatures],
    observations: ObservationTable,
    landmark_id: I64,
    landmark_p_nav_m: F64,
    landmark_desc: U8 | None,
    landmark_true_id: I64,
    max_descriptors: int,
) -> tuple[Points, Observed]:
    """Re-association's start (`reassociation.py`): every map landmark (`landmark_id` (L,),
    positions (L, 3), the archive's descriptors (L, D) or None, simulator ids (L,)) as a
    point, and the filter's observations made at the keyframes of `vehicles` (features
    `features`, one per vehicle) as the base observations, each with its feature row (found
    by its pixels) and the landmark's descriptors from those features. A landmark with no
    descriptor at all (none found, no archive) is never predicted: it keeps only the
    filter's observations."""
    names = [v.name for v in vehicles]
    to_problem = np.array(
        [names.index(n) if n in names else -1 for n in observations.vehicles], dtype=np.int64
    )
    obs_vehicle = to_problem[observations.vehicle] if len(observations) else observations.vehicle
    kept = keep_observations(
        obs_vehicle, observations.stamp_ns, observations.landmark_id,
        [v.stamps_ns for v in vehicles], min_keyframes=1,
    )  # fmt: skip
    row_of = {int(i): r for r, i in enumerate(landmark_id)}
    missing = [int(i) for i in kept.landmark_ids if int(i) not in row_of]
    if missing:
        raise ValueError(f"observed landmark ids not in the map: {missing[:5]}")
    point = np.array([row_of[int(i)] for i in kept.landmark_ids], dtype=np.int64)[kept.landmark]
    v_of = obs_vehicle[kept.rows]
    z = observations.z_px[kept.rows]
    feature = np.full(len(kept.rows), -1, dtype=np.int64)
    for v, kf in enumerate(features):
        sel = np.flatnonzero(v_of == v)
        feature[sel] = find_rows(kf, kept.keyframe[sel], z[sel])
    base = Observed(v_of, kept.keyframe, point, feature, z, np.ones(len(point), dtype=bool))
    found = feature >= 0
    desc = np.zeros((int(found.sum()), features[0].desc.shape[1] if features else 128), np.uint8)
    for v, kf in enumerate(features):
        sel = v_of[found] == v
        desc[sel] = kf.desc[feature[found][sel]]
    sets, n_desc = descriptor_sets(
        len(landmark_id), point[found], desc, max_descriptors, start=landmark_desc
    )
    points = Points(
        np.asarray(landmark_id, dtype=np.int64), np.asarray(landmark_p_nav_m, dtype=float),
        sets, n_desc, np.asarray(landmark_true_id, dtype=np.int64),
    )  # fmt: skip
    return points, base
