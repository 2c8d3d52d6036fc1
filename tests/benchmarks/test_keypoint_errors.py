"""`make bench`: what the simulated images' keypoint errors are, against the truth (issue 15).

The filter models each pixel coordinate of a stereo observation (u_l, v_l, u_r, v_r) as
independent white noise. This benchmark measures how far the errors of the observations a
filter run actually used are from that: every landmark of the run's
`fuse/observations.npz` seen by one vehicle in at least MIN_OBSERVATIONS frames is placed by
least squares over all its stereo observations with the simulator's *true* poses, and the
residuals (observation minus the projection of that point) are read in the components the
stereo geometry gives them (BENCHMARKS.md, "Fuse: what the simulated images' keypoint errors
are"):

- bearing u = (u_l + u_r) / 2, disparity d = u_l - u_r, bearing v = (v_l + v_r) / 2 and
  v_l - v_r: their standard deviations (independent noise sigma per coordinate gives
  sigma / sqrt 2, sigma sqrt 2, sigma / sqrt 2, sigma sqrt 2) and 1.4826 x their median
  absolute deviation (the core of a long-tailed error), the left-right correlations of
  u and v, and each component's autocorrelation along a landmark's track at lags of 1 to 15
  frames (white noise reads about -1 / track length: the fit's own bias), over the tracks
  without a gross residual (a wrong association or a failed fit: beyond OUTLIER_SIGMAS
  robust sigmas);
- the spread of the mean residual over each frame's landmarks against what independent errors
  give (an error common to a frame: timing or pose);
- the same standard deviations by the left keypoint's SIFT octave (0, 1, 2, 3 and coarser),
  and the bearing's lag-1 autocorrelation over the tracks of each (a track's median octave):
  what `fuse.association.octave_bearing_variance` models (estimation/octave_noise.py).

Printed, and written to `runs/benchmarks/keypoint_errors.csv` and
`keypoint_errors_by_octave.csv` (gitignored); asserted only
that the analysis found landmarks and finite figures (DESIGN.md convention 8: the issue notes
judge the figures). Data: the layout of `test_fuse_images_seeds.py` under CVSLAM_IMAGES_SIM
(base/<scenario>_<seed>/{sim,run}); missing parts are made (simulate, extract, fuse for
`uav2_paper`'s 60 s), so after that benchmark this one costs only its analysis (6 s; 100 s
from nothing).
Environment: CVSLAM_KEYPOINT_SCENARIO (default uav2_paper), CVSLAM_KEYPOINT_SEED (default 1),
CVSLAM_KEYPOINT_VEHICLE (default the first).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.geometry.camera import stereo_rig
from cvslam_cli.geometry.rotations import matrix_to_euler_zyx, quat_xyzw_to_matrix
from cvslam_cli.geometry.stereo import projection_matrices, triangulate
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.observations_file import load_observations
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.records.features import FeatureSet
from tests.benchmarks.test_fuse_images_seeds import OUT, _cvslam, prepared

SCENARIO = os.environ.get("CVSLAM_KEYPOINT_SCENARIO", "uav2_paper")
SEED = int(os.environ.get("CVSLAM_KEYPOINT_SEED", "1"))
VEHICLE = os.environ.get("CVSLAM_KEYPOINT_VEHICLE", "")
MIN_OBSERVATIONS = 8
OUTLIER_SIGMAS = 20.0
LAGS = (1, 2, 3, 5, 10, 15)
OCTAVE_GROUPS = 4  # octaves 0, 1, 2, and 3 or coarser
COMPONENTS = ("bearing u", "disparity", "bearing v", "v_l - v_r")
# (u_l, v_l, u_r, v_r) -> the components above
TO_COMPONENTS = np.array(
    [[0.5, 0.0, 0.5, 0.0], [1.0, 0.0, -1.0, 0.0], [0.0, 0.5, 0.0, 0.5], [0.0, 1.0, 0.0, -1.0]]
)


def _run_folder(base: Path) -> tuple[Path, Path]:
    """(sim, run) with the run's cooperative fuse made if missing."""
    sim, run = prepared(base, SCENARIO, SEED)
    if not (run / "fuse" / "observations.npz").is_file():
        _cvslam("fuse", run, "--force")
    return sim, run


def _true_poses(sim: Path, vehicle: str, stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions (K, 3), euler (K, 3)) of the truth at exactly these stamps (the simulator
    writes a true pose at every camera frame)."""
    truth = read_tum(sim / "truth" / f"{vehicle}.tum")
    i = np.searchsorted(truth.stamps_ns, stamps_ns)
    i = np.clip(i, 0, len(truth) - 1)
    assert np.all(np.abs(truth.stamps_ns[i] - stamps_ns) < 1000), "no true pose at a frame"
    euler = np.array(
        [matrix_to_euler_zyx(quat_xyzw_to_matrix(q)) for q in truth.q_nav_body_xyzw[i]]
    )
    return truth.p_nav_m[i], euler


def _point_fit(
    obs: StereoObservationModel,
    M: tuple[np.ndarray, np.ndarray],
    p: np.ndarray,
    e: np.ndarray,
    z: np.ndarray,
) -> np.ndarray:
    """Residuals (k, 4) of one landmark's k observations z at true poses (p, e) about the
    point that fits them best (Gauss-Newton from the first observation's stereo point,
    triangulated with the rig's projection matrices M)."""
    p_cam = triangulate(*M, z[:1, :2], z[:1, 2:])
    X = obs.landmark_jacobians(p[0], e[0], p_cam)[0][0]
    for _ in range(10):
        r, J = [], []
        for j in range(len(z)):
            zj, _, Hm = obs.predict(p[j], e[j], X[None])
            r.append(z[j] - zj[0])
            J.append(Hm[0])
        r_all, J_all = np.concatenate(r), np.concatenate(J)
        step = np.linalg.lstsq(J_all, r_all, rcond=None)[0]
        X = X + step
        if np.max(np.abs(step)) < 1e-6:
            break
    return np.array([z[j] - obs.predict(p[j], e[j], X[None])[0][0] for j in range(len(z))])


def _octaves(fs: FeatureSet, stamps_ns: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(k,) the left keypoint's octave of each observation (the frame's stereo match whose
    left pixel it is; -99 where none is, which does not happen for a run's own features)."""
    frame = np.searchsorted(fs.frame_stamp_ns, stamps_ns)
    out = np.full(len(z), -99, dtype=np.int64)
    for f in np.unique(frame):
        left = fs.match_left[fs.frame_matches(int(f))]
        uv = fs.left_uv_px[left].astype(float)
        rows = np.flatnonzero(frame == f)
        d = np.abs(uv[None, :, :] - z[rows, None, :2]).sum(axis=2)
        j = d.argmin(axis=1)
        ok = d[np.arange(len(rows)), j] < 1e-3
        out[rows[ok]] = fs.left_octave[left[j[ok]]]
    return out


def _by_octave(tracks: list[np.ndarray], octaves: list[np.ndarray]) -> pd.DataFrame:
    """Per octave group (0, 1, 2, 3 and coarser): the components' std and robust std, and
    the bearing u's lag-1 autocorrelation over the tracks whose median octave is in it."""
    # an upsampled image's octave -1 counts as octave 0 (as octave_noise.py reads it)
    comp, octv = np.concatenate(tracks), np.clip(np.concatenate(octaves), 0, OCTAVE_GROUPS - 1)
    track_group = [int(np.clip(np.median(o), 0, OCTAVE_GROUPS - 1)) for o in octaves]
    rows = []
    for g in range(OCTAVE_GROUPS):
        k = octv == g
        if k.sum() < 30:
            continue
        row: dict[str, float | int | str] = {
            "octave": f"{g}" + ("+" if g == OCTAVE_GROUPS - 1 else ""),
            "n": int(k.sum()),
        }
        for c, name in enumerate(COMPONENTS[:3]):
            x = comp[k, c]
            row[f"{name} std_px"] = float(x.std())
            row[f"{name} robust_px"] = 1.4826 * float(np.median(np.abs(x - np.median(x))))
        mine = [t[:, 0] for t, tg in zip(tracks, track_group, strict=True) if tg == g]
        row["bearing u acf lag1"] = _autocorrelation(mine, 1)
        rows.append(row)
    return pd.DataFrame(rows)


def _autocorrelation(tracks: list[np.ndarray], lag: int) -> float:
    """Pooled autocorrelation at `lag` of the tracks' demeaned series."""
    num = den = 0.0
    for x in tracks:
        x = x - x.mean()
        if len(x) > lag:
            num += float(np.sum(x[:-lag] * x[lag:]))
            den += float(np.sum(x * x)) * (len(x) - lag) / len(x)
    return num / den if den else float("nan")


def test_keypoint_error_structure() -> None:
    base_env = os.environ.get("CVSLAM_IMAGES_SIM")
    with tempfile.TemporaryDirectory(prefix="cvslam_keypoints_") as tmp:
        sim, run = _run_folder(Path(base_env) if base_env else Path(tmp))
        table = load_observations(run / "fuse" / "observations.npz")
        vehicle = VEHICLE or table.vehicles[0]
        fs, _ = load_features(run / "features" / f"{vehicle}.npz")
        rig = stereo_rig(fs.rig)
        obs, M = StereoObservationModel.from_rig(rig), projection_matrices(rig)
        mine = table.vehicle == table.vehicles.index(vehicle)
        lid, st, z = table.landmark_id[mine], table.stamp_ns[mine], table.z_px[mine]
        order = np.lexsort((st, lid))
        lid, st, z = lid[order], st[order], z[order]
        p_all, e_all = _true_poses(sim, vehicle, st)
        starts = np.flatnonzero(np.r_[True, lid[1:] != lid[:-1]])
        octave = _octaves(fs, st, z)
        tracks, stamps, octaves = [], [], []
        for s0, s1 in zip(starts, np.r_[starts[1:], len(lid)], strict=True):
            if s1 - s0 >= MIN_OBSERVATIONS:
                res = _point_fit(obs, M, p_all[s0:s1], e_all[s0:s1], z[s0:s1])
                tracks.append(res @ TO_COMPONENTS.T)
                stamps.append(st[s0:s1])
                octaves.append(octave[s0:s1])
    assert tracks, f"no landmark of {vehicle} seen {MIN_OBSERVATIONS} times or more"
    # a track holding a wrong association (or a fit that failed) is no sample of the noise:
    # kept are the tracks whose every residual lies within OUTLIER_SIGMAS robust sigmas (wide:
    # SIFT's errors have a long tail, which a narrower cut would take for wrong associations)
    pooled = np.concatenate(tracks)
    robust = 1.4826 * np.median(np.abs(pooled - np.median(pooled, axis=0)), axis=0)
    keep = [bool(np.all(np.abs(t) <= OUTLIER_SIGMAS * robust)) for t in tracks]
    n_all = len(tracks)
    tracks = [t for t, k in zip(tracks, keep, strict=True) if k]
    stamps = [t for t, k in zip(stamps, keep, strict=True) if k]
    octaves = [t for t, k in zip(octaves, keep, strict=True) if k]
    comp = np.concatenate(tracks)
    raw = comp @ np.linalg.inv(TO_COMPONENTS).T  # back to (u_l, v_l, u_r, v_r)
    rows = []
    for c, name in enumerate(COMPONENTS):
        acf = [_autocorrelation([t[:, c] for t in tracks], lag) for lag in LAGS]
        mad = float(np.median(np.abs(comp[:, c] - np.median(comp[:, c]))))
        rows.append({"component": name, "std_px": float(comp[:, c].std()),
                     "robust_std_px": 1.4826 * mad,
                     **{f"acf_lag{lag}": a for lag, a in zip(LAGS, acf, strict=True)}})  # fmt: skip
    df = pd.DataFrame(rows)
    lr_u = float(np.corrcoef(raw[:, 0], raw[:, 2])[0, 1])
    lr_v = float(np.corrcoef(raw[:, 1], raw[:, 3])[0, 1])
    # an error common to a frame: the mean residual over each frame's landmarks
    frame_of = np.concatenate(stamps)
    centred = np.concatenate([t - t.mean(axis=0) for t in tracks])
    means, counts = [], []
    for s in np.unique(frame_of):
        k = frame_of == s
        if k.sum() >= 10:
            means.append(centred[k, 0].mean())
            counts.append(k.sum())
    OUT.mkdir(parents=True, exist_ok=True)
    df.to_csv(OUT / "keypoint_errors.csv", index=False)
    assert np.all(np.concatenate(octaves) >= -1), "an observation with no stereo match"
    by_octave = _by_octave(tracks, octaves)
    by_octave.to_csv(OUT / "keypoint_errors_by_octave.csv", index=False)
    lengths = [len(t) for t in tracks]
    print(
        f"\n{SCENARIO} seed {SEED}, {vehicle}: {n_all} landmarks with >= {MIN_OBSERVATIONS}"
        f" observations, {len(tracks)} of them with every residual within {OUTLIER_SIGMAS}"
        f" robust sigmas (median track {int(np.median(lengths))}), residuals against the point"
        f" fitted with the true poses; per coordinate u_l / v_l / u_r / v_r std "
        + " / ".join(f"{s:.3f}" for s in raw.std(axis=0))
        + " px"
    )
    print(df.round(3).to_string(index=False))
    print(f"left-right correlation: u {lr_u:.2f}, v {lr_v:.2f}")
    if means:
        expected = comp[:, 0].std() / np.sqrt(np.mean(counts))
        print(
            f"mean bearing-u residual over a frame's landmarks ({len(means)} frames): std"
            f" {np.std(means):.3f} px (independent errors: {expected:.3f})"
        )
    print("by the left keypoint's octave:")
    print(by_octave.round(3).to_string(index=False))
    print(f"tables: {OUT / 'keypoint_errors.csv'}, {OUT / 'keypoint_errors_by_octave.csv'}")
    assert np.all(np.isfinite(df["std_px"]))
