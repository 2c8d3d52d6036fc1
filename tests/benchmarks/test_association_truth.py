"""`make bench`: the filter's associations against the simulator's truth (issues 15 and 20).

On the images runs one wrong association moves a whole run (BENCHMARKS.md, "Fuse: ten more
seeds, a window limit, and seed 14"), and the end errors move between seeds by more than most
changes of the association move them. This benchmark reads the associations themselves:
every observation a cooperative filter run used (`fuse/observations.npz`) is checked against
the simulator's per-pixel true depth (`cvslam simulate --set outputs.depth=true`).

- A stereo match's true point is the ground under its left keypoint: the median true depth of
  the 3 x 3 pixels around it, along the keypoint's ray from the camera's true pose.
- A landmark's true point is that of its first observation (at a stamp several vehicles
  observed it first, the one of them with most observations of it: its reference vehicle).
- An observation's residual is the distance (px) between its left keypoint and the
  projection of its landmark's true point from the observer's true pose; above
  WRONG_PX it is a wrong association (another point of the ground).

Printed per seed, for observations by the landmark's reference vehicle ("own") and by another
vehicle ("cross"): how many, the median residual, the share wrong; the share of
(landmark, vehicle) tracks of at least MIN_TRACK observations whose median residual is above
OFFSET_PX (a keypoint that another view places persistently elsewhere: white noise does not
do that); and the first cross-vehicle association of each (landmark, vehicle) pair, the
share wrong; then per (observer, mapper) pair of vehicles the observations, their median
residual and the share wrong (in a mixed team, which kinds of view fail each other). Written
to `runs/benchmarks/association_truth.csv` and `association_truth_pairs.csv` (gitignored);
asserted only that observations were checked and the figures are finite (DESIGN.md
convention 8).

Data: the layout of `test_fuse_images_seeds.py` under CVSLAM_IMAGES_SIM (simulated and
extracted there unless kept). The true depth is simulated once more beside it (the same
images, with depth: ~0.8 GB per seed), read at the matches into `true_depth.npz` and
deleted; the cooperative filter runs in `run_truth` on the same features with the overrides
CVSLAM_TRUTH_SET (";"-separated). Environment: CVSLAM_TRUTH_SCENARIO (default uav2_paper),
CVSLAM_TRUTH_SEEDS (default "1"), CVSLAM_IMAGES_SIMULATE_SET (the simulation's overrides, for
both simulations, e.g. "duration_s=30"). Time: ~40 s per seed kept (its fuse), ~4 min from
nothing.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.geometry.camera import stereo_rig
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.observations_file import load_observations
from cvslam_cli.records.features import FeatureSet
from cvslam_cli.records.observations import ObservationTable
from tests.benchmarks.test_fuse_images_seeds import (
    OUT,
    _baseline_run,
    _cvslam,
    _overrides,
    _set_args,
    prepared,
    simulate_sets,
)
from tests.benchmarks.test_keypoint_errors import _true_poses

WRONG_PX = 3.0
OFFSET_PX = 1.0
MIN_TRACK = 5


def _true_depth(base: Path, scenario: str, seed: int, vehicles: list[str]) -> dict[str, np.ndarray]:
    """{vehicle: (M,) true depth (m) under each stereo match's left keypoint}, cached in
    base/<scenario>_<seed>/true_depth.npz (the depth simulation deleted after reading)."""
    folder = base / f"{scenario}_{seed}"
    cache = folder / "true_depth.npz"
    if not cache.is_file():
        sim_depth = folder / "sim_depth"
        _cvslam("simulate", scenario, "-o", sim_depth, "--seed", seed, "--force",
                "--set", "outputs.depth=true", *simulate_sets())  # fmt: skip
        depths = {}
        for v in vehicles:
            fs, _ = load_features(folder / "run" / "features" / f"{v}.npz")
            depths[v] = _depth_at_matches(sim_depth / "truth" / f"{v}_depth.npz", fs)
        np.savez(cache, **depths)
        shutil.rmtree(sim_depth)
    with np.load(cache) as z:
        return {v: z[v] for v in vehicles}


def _depth_at_matches(depth_file: Path, fs: FeatureSet) -> np.ndarray:
    """(M,) the median true depth of the 3 x 3 pixels around each match's left keypoint."""
    out = np.full(len(fs.match_left), np.nan)
    with np.load(depth_file) as depth:
        assert len(depth.files) == len(fs.frame_stamp_ns), f"{depth_file}: frames differ"
        for f in range(len(fs.frame_stamp_ns)):
            rows = np.arange(fs.match_offsets[f], fs.match_offsets[f + 1])
            if not len(rows):
                continue
            D = depth[f"frame_{f:06d}"].astype(float)
            uv = fs.left_uv_raw_px[fs.match_left[rows]]
            c = np.clip(np.rint(uv[:, 0]).astype(int), 1, D.shape[1] - 2)
            r = np.clip(np.rint(uv[:, 1]).astype(int), 1, D.shape[0] - 2)
            patch = np.stack([D[r + i, c + j] for i in (-1, 0, 1) for j in (-1, 0, 1)], axis=1)
            out[rows] = np.nanmedian(patch, axis=1)
    return out


def _frames(fs: FeatureSet, stamps_ns: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(frame of fs, rows of stamps_ns (n,) on it) for each frame they fall on (exactly)."""
    f = np.searchsorted(fs.frame_stamp_ns, stamps_ns)
    assert np.all(fs.frame_stamp_ns[np.clip(f, 0, len(fs.frame_stamp_ns) - 1)] == stamps_ns)
    return [(int(frame), np.flatnonzero(f == frame)) for frame in np.unique(f)]


def _true_points(
    fs: FeatureSet, depth: np.ndarray, obs: StereoObservationModel,
    frames: list[tuple[int, np.ndarray]], p: np.ndarray, e: np.ndarray, z_px: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """(n, 3) nav-frame true points under the left keypoints z_px[:, :2] (each one of its
    frame's stereo matches), the camera at the true poses p, e (n, 3) of `frames` (rows of
    the n observations, one group per frame)."""
    K = obs.K[0]
    out = np.empty((len(z_px), 3))
    for frame, k in frames:
        rows = np.arange(fs.match_offsets[frame], fs.match_offsets[frame + 1])
        uv = fs.left_uv_px[fs.match_left[rows]].astype(float)
        d = np.linalg.norm(z_px[k, None, :2] - uv[None], axis=2)
        nearest = np.argmin(d, axis=1)
        assert np.all(d[np.arange(len(k)), nearest] < 1e-2), "an observation is no match"
        zc = depth[rows[nearest]]
        y = (z_px[k, 1] - K[1, 2]) / K[1, 1] * zc
        x = (z_px[k, 0] - K[0, 2] - K[0, 1] * y / zc) / K[0, 0] * zc
        out[k] = obs.landmark_jacobians(p[k[0]], e[k[0]], np.stack([x, y, zc], axis=1))[0]
    return out


def _residuals(
    sim: Path, run: Path, t: ObservationTable, depths: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """(residual px (N,), reference (N,): the index in t.vehicles of each observation's
    landmark's reference vehicle; by another vehicle, a cross-vehicle observation)."""
    points = np.full((len(t.stamp_ns), 3), np.nan)
    views = []  # per vehicle: (rows, model, frames, true p, true e)
    for i, v in enumerate(t.vehicles):
        fs, _ = load_features(run / "features" / f"{v}.npz")
        model = StereoObservationModel.from_rig(stereo_rig(fs.rig))
        k = np.flatnonzero(t.vehicle == i)
        frames = _frames(fs, t.stamp_ns[k])
        p, e = _true_poses(sim, v, t.stamp_ns[k])
        points[k] = _true_points(fs, depths[v], model, frames, p, e, t.z_px[k])
        views.append((k, model, frames, p, e))
    # each landmark's reference: the first stamp, then the vehicle with most observations
    n_by = pd.Series(1, index=pd.MultiIndex.from_arrays([t.landmark_id, t.vehicle])).groupby(
        level=[0, 1]).sum()  # fmt: skip
    counts = n_by.reindex(pd.MultiIndex.from_arrays([t.landmark_id, t.vehicle])).to_numpy()
    order = np.lexsort((-counts, t.stamp_ns, t.landmark_id))
    lid_sorted = t.landmark_id[order]
    first = order[np.r_[True, lid_sorted[1:] != lid_sorted[:-1]]]
    ref = pd.Series(first, index=t.landmark_id[first])
    ref_row = ref.reindex(t.landmark_id).to_numpy()
    residual = np.full(len(t.stamp_ns), np.nan)
    for k, model, frames, p, e in views:
        for _, g in frames:
            rows = k[g]
            zp = model.predict(p[g[0]], e[g[0]], points[ref_row[rows]])[0]
            residual[rows] = np.hypot(*(t.z_px[rows, :2] - zp[:, :2]).T)
    return residual, t.vehicle[ref_row]


def _pairs(
    seed: int, t: ObservationTable, residual: np.ndarray, reference: np.ndarray
) -> list[dict]:
    """Per (observer, mapper) pair of vehicles, the mapper the landmarks' reference: how
    many observations, their median residual and the share wrong (a mixed team's kinds of
    vehicle see one surface differently: which pairs fail)."""
    ok = np.isfinite(residual)
    names = np.asarray(t.vehicles)
    frame = pd.DataFrame(
        {"observer": names[t.vehicle[ok]], "mapper": names[reference[ok]], "r": residual[ok]}
    )
    return [
        {"seed": seed, "observer": o, "mapper": m, "observations": len(g),
         "median_px": float(g.r.median()), "wrong_share": float((g.r > WRONG_PX).mean())}
        for (o, m), g in frame.groupby(["observer", "mapper"])
    ]  # fmt: skip


def _summary(seed: int, t: ObservationTable, residual: np.ndarray, cross: np.ndarray) -> list[dict]:
    """Rows of the printed table (module docstring), one for own and one for cross."""
    ok = np.isfinite(residual)
    frame = pd.DataFrame({"lid": t.landmark_id, "veh": t.vehicle, "stamp": t.stamp_ns,
                          "r": residual, "cross": cross})[ok]  # fmt: skip
    rows = []
    for name, part in (("own", frame[~frame.cross]), ("cross", frame[frame.cross])):
        tracks = part.groupby(["lid", "veh"])["r"].agg(["median", "size"])
        tracks = tracks[tracks["size"] >= MIN_TRACK]
        firsts = part.sort_values("stamp", kind="stable").groupby(["lid", "veh"]).head(1)
        rows.append({
            "seed": seed, "kind": name, "observations": len(part),
            "median_px": float(part.r.median()) if len(part) else np.nan,
            "wrong_share": float((part.r > WRONG_PX).mean()) if len(part) else np.nan,
            "tracks": len(tracks),
            "offset_track_share": float((tracks["median"] > OFFSET_PX).mean())
            if len(tracks) else np.nan,
            # own: a landmark's first observation made it (its residual is 0 by definition)
            "first_associations": len(firsts) if name == "cross" else 0,
            "first_wrong_share": float((firsts.r > WRONG_PX).mean())
            if name == "cross" and len(firsts) else np.nan,
            "unseen_share": float(1.0 - ok[cross == (name == "cross")].mean()),
        })  # fmt: skip
    return rows


def test_associations_against_the_truth() -> None:
    scenario = os.environ.get("CVSLAM_TRUTH_SCENARIO", "uav2_paper")
    seeds = [int(s) for s in os.environ.get("CVSLAM_TRUTH_SEEDS", "1").split(",")]
    sets = _overrides("CVSLAM_TRUTH_SET") or []
    kept = os.environ.get("CVSLAM_IMAGES_SIM")
    rows: list[dict] = []
    pairs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="cvslam_association_truth_") as tmp:
        base = Path(kept) if kept else Path(tmp)
        for seed in seeds:
            sim, run = prepared(base, scenario, seed)
            work = _baseline_run(run, "run_truth")
            _cvslam("fuse", work, "--force", *_set_args(sets))
            t = load_observations(work / "fuse" / "observations.npz")
            depths = _true_depth(base, scenario, seed, list(t.vehicles))
            residual, reference = _residuals(sim, work, t, depths)
            rows += _summary(seed, t, residual, t.vehicle != reference)
            pairs += _pairs(seed, t, residual, reference)
    table = pd.DataFrame(rows)
    OUT.mkdir(parents=True, exist_ok=True)
    table.to_csv(OUT / "association_truth.csv", index=False)
    pd.DataFrame(pairs).to_csv(OUT / "association_truth_pairs.csv", index=False)
    print(f"\n{scenario} with images, seeds {seeds}, overrides {sets or 'none'}: associations "
          f"against the true depth (wrong: > {WRONG_PX:g} px; offset track: median > "
          f"{OFFSET_PX:g} px over >= {MIN_TRACK} observations)")  # fmt: skip
    print(table.round(4).to_string(index=False))
    for kind, part in table.groupby("kind", sort=False):
        w = part.observations.to_numpy(float)
        f = part.first_associations.to_numpy(float)
        wrong = np.sum(part.wrong_share * w) / w.sum()
        first_wrong = np.nansum(part.first_wrong_share * f) / max(f.sum(), 1)
        firsts = f"; first associations {int(f.sum())}, wrong {first_wrong:.2%}" if f.sum() else ""
        print(f"{kind}: {int(w.sum())} observations, wrong {wrong:.2%}{firsts}")
    print("by observer and mapper (the landmark's reference vehicle):")
    print(pd.DataFrame(pairs).round(4).to_string(index=False))
    assert table.observations.sum() > 0
    assert np.isfinite(table[["median_px", "wrong_share"]].to_numpy(float)).all()
