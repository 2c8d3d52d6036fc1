"""`cvslam refine`: the batch solution over a fuse run (package docstring, docs/refine.md).

Inputs: `<run>/<source>/` (a fuse folder: trajectories, `map.csv`, `observations.npz`), the
run's features (rig, pixel noise) and logs (motion data, the filter's initial poses).
Outputs, in `<run>/fuse_refined/` (`<source>_refined/` for another source), the fuse
folder's formats (docs/fuse_outputs.md), written to a temporary folder renamed when
complete: per vehicle `<v>.tum` (the keyframes' refined poses), `<v>_pose_cov.npz` (their
marginal covariances), `<v>_deadreckoning.tum` (the source's, for the same comparisons);
`map.csv`, `map.ply` (every landmark of the source map: the refined ones moved, with their
marginal standard deviations), `map.npz` (the source's map file refined likewise, with the
tracks' new points: `map_archive.py`; a later run's prior map), `result.mcap`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from cvslam_cli import __version__
from cvslam_cli.config import Config
from cvslam_cli.errors import CvslamError
from cvslam_cli.estimation.stage import FALLBACK_PIXEL_SIGMA_PX, build_inputs
from cvslam_cli.geometry.rotations import interpolate_positions, matrix_to_quat_xyzw
from cvslam_cli.io.atomic import atomic_dir, check_writable
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.fuse_files import (
    read_map_csv,
    save_pose_covariances,
    write_map_csv,
    write_map_ply,
)
from cvslam_cli.io.logs import all_log_paths, open_logs, require_logs, with_run_bindings
from cvslam_cli.io.map_file import load_map, save_map
from cvslam_cli.io.observations_file import load_observations
from cvslam_cli.io.result_mcap import write_result_mcap
from cvslam_cli.io.run_layout import FuseFolder, RunLayout, refined_name
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.trajectory import read_tum, write_tum
from cvslam_cli.records.landmark_archive import LandmarkArchive
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.poses import PoseTable
from cvslam_cli.refine import graph, right_cx
from cvslam_cli.refine.build import build_problem, reassociation_start
from cvslam_cli.refine.keyframe_features import keyframe_features
from cvslam_cli.refine.map_archive import observed, refined_archive
from cvslam_cli.refine.marginals import IndeterminateError
from cvslam_cli.refine.problem import RefineProblem, RefineResult, RefineSettings
from cvslam_cli.refine.reassociation import ReassociationSettings
from cvslam_cli.refine.rounds import RoundsResult, RoundStats, run_rounds

log = logging.getLogger("cvslam.refine")


@dataclass(frozen=True)
class VehicleRefine:
    keyframes: int
    model: str
    rmse_source_m: float  # position RMSE of the source at the keyframes (nan: no truth)
    rmse_m: float
    prior_sigma_position_m: float  # the gauge: the prior on the first keyframe
    prior_sigma_attitude_rad: float
    right_cx_px: float  # the right camera's u0 correction and its std (nan: not estimated)
    right_cx_std_px: float


@dataclass(frozen=True)
class RefineSummary:
    out_dir: Path
    skipped: bool
    source: str
    vehicles: dict[str, VehicleRefine]
    landmarks: int
    observations: int
    factors: dict[str, int]
    iterations: int
    initial_error: float
    final_error: float
    outliers: int
    pixel_sigma_px: float
    wall_s: float
    rounds: tuple[RoundStats, ...] = ()
    removed_by_check: int = 0


# --------------------------------------------------------------------------- inputs


def feature_pixel_sigma(metas: Sequence[dict[str, Any]]) -> float | None:
    """The pixel noise the features were made with: extract's `stereo.pixel_sigma_px`, or the
    simulator's landmark-mode `pixel_noise_px`; the largest over the files, None if unknown."""
    found = []
    for meta in metas:
        sigma = meta.get("config", {}).get("stereo", {}).get("pixel_sigma_px")
        if sigma is None:
            sigma = meta.get("landmarks", {}).get("pixel_noise_px")
        if sigma is not None:
            found.append(float(sigma))
    return max(found) if found else None


def extract_right_cx(metas: Sequence[dict[str, Any]], problem: RefineProblem) -> np.ndarray:
    """(V,) the right-camera u0 correction each vehicle's feature file already holds
    (`extract.stereo.calibrate_disparity_offset` moves u0 by -offset_px; 0 without it), so
    that refine's own estimate keeps its prior on the calibration."""
    applied = {
        m.get("vehicle"): -float(m.get("disparity_offset", {}).get("applied_px", 0.0))
        for m in metas
    }
    return np.array([applied.get(v.name, 0.0) for v in problem.vehicles])


def fuse_right_cx(record: dict[str, Any], source: str, problem: RefineProblem) -> np.ndarray:
    """(V,) the right-camera u0 correction the fuse run `source` estimated and used (its
    calibration pass, `estimation/rig_calibration.py`, recorded in run.yaml; 0 where it did
    not): the map and trajectories refine starts from were made with it."""
    done = record.get("stages", {}).get(source, {}).get("summary", {}).get("right_cx_px", {})
    return np.array([float(done.get(v.name, {}).get("value", 0.0)) for v in problem.vehicles])


def settings_of(cfg: Config, metas: Sequence[dict[str, Any]]) -> RefineSettings:
    rc = cfg.refine
    sigma = rc.pixel_sigma_px
    if sigma == 0:
        known = feature_pixel_sigma(metas)
        if known is None:
            fused = cfg.fuse.association.pixel_sigma_px
            sigma = FALLBACK_PIXEL_SIGMA_PX if fused == "auto" else fused
            log.warning(
                "refine: the feature files do not say their pixel noise; using %g px "
                "(fuse.association.pixel_sigma_px %s; refine.pixel_sigma_px to set it)",
                sigma,
                fused,
            )
        else:
            sigma = known
    return RefineSettings(
        pixel_sigma_px=sigma,
        robust=rc.robust,
        robust_k=rc.robust_k,
        planar_sigma=rc.planar_sigma,
        max_iterations=rc.max_iterations,
        relative_error_tol=rc.relative_error_tol,
        ordering=rc.ordering,
        landmark_covariances=rc.landmark_covariances,
        estimate_right_cx=rc.estimate_right_cx,
        right_cx_sigma_px=rc.right_cx_sigma_px,
    )


def _source_files(src: FuseFolder, vehicles: Sequence[str]) -> list[Path]:
    """The source fuse folder's files refine reads; CvslamError naming the first missing."""
    files = [src.map_csv, src.observations, *(src.trajectory(v) for v in vehicles)]
    for path in files:
        if not path.exists():
            remedy = (
                "it was written by a cvslam without observations: run `cvslam fuse --force`"
                if path == src.observations and src.map_csv.exists()
                else f"run `cvslam fuse` first ({src.name})"
            )
            raise CvslamError(f"{path}: not found; {remedy}")
    return files


# --------------------------------------------------------------------------- outputs


def _pose_table(stamps_ns: np.ndarray, T: np.ndarray) -> PoseTable:
    q = np.array([matrix_to_quat_xyzw(t[:3, :3]) for t in T]).reshape(-1, 4)
    return PoseTable(stamps_ns.astype(np.int64), T[:, :3, 3].copy(), q)


def refined_map(
    source: LandmarkMap,
    problem: RefineProblem,
    res: RefineResult,
    true_id: np.ndarray | None = None,
) -> LandmarkMap:
    """The source map with the refined landmarks moved (and their marginal std devs), and
    the new points of re-association's tracks (ids not in the source map) appended, with
    their observers, observation counts and times from the problem and `true_id` (L,) (the
    problem's landmarks' simulator ids; None: unknown), of the source's latest session."""
    p = source.p_nav_m.copy()
    std = source.std_m.copy()
    row_of = {int(i): r for r, i in enumerate(source.landmark_id)}
    known = np.array([int(i) in row_of for i in problem.landmark_id], dtype=bool)
    rows = np.array([row_of[int(i)] for i in problem.landmark_id[known]], dtype=np.int64)
    std_new = np.sqrt(np.maximum(np.diagonal(res.cov, axis1=1, axis2=2), 0.0))
    if len(rows):
        p[rows] = res.p_nav_m[known]
        std[rows] = std_new[known]
    out = dataclasses.replace(source, p_nav_m=p, std_m=std)
    new = np.flatnonzero(~known)
    if not len(new):
        return out
    obs = observed(problem, new, res.p_nav_m[new])
    tid = np.full(len(new), -1, dtype=np.int64) if true_id is None else true_id[new]
    assert out.session is not None  # LandmarkMap fills it
    latest = int(out.session.max()) if len(out.session) else 0  # the new points' session
    return LandmarkMap(
        np.concatenate([out.landmark_id, problem.landmark_id[new]]),
        np.vstack([out.p_nav_m, res.p_nav_m[new]]),
        np.vstack([out.std_m, std_new[new]]),
        (*out.observers, *obs.observers([v.name for v in problem.vehicles])),
        np.concatenate([out.n_observations, obs.count]),
        np.concatenate([out.first_seen_ns, obs.first_ns]),
        np.concatenate([out.last_seen_ns, obs.last_ns.max(axis=1)]),
        np.concatenate([out.in_state, np.zeros(len(new), dtype=bool)]),
        np.concatenate([out.true_id, tid]),
        np.concatenate([out.session, np.full(len(new), latest, dtype=np.int64)]),
    )


def _rmse(table: PoseTable, truth: PoseTable | None) -> float:
    if truth is None or len(truth) == 0 or len(table) == 0:
        return float("nan")
    e = np.linalg.norm(
        table.p_nav_m - interpolate_positions(truth.stamps_ns, truth.p_nav_m, table.stamps_ns),
        axis=1,
    )
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def _header(source: str) -> str:
    return f"cvslam {__version__} refine (of {source}), nav frame NED, body FRD"


def _write(
    out: FuseFolder,
    src: FuseFolder,
    tables: dict[str, PoseTable],
    res: RefineResult,
    lm: LandmarkMap,
    archive: LandmarkArchive | None,
    source: str,
) -> None:
    header = _header(source)
    if archive is not None:
        save_map(out.map_npz, archive)
    dr = {}
    for v in res.vehicles:
        write_tum(out.trajectory(v.name), tables[v.name], header=f"{header}\nvehicle {v.name}")
        save_pose_covariances(out.pose_covariances(v.name), v.stamps_ns, v.pose_cov)
        dr_path = src.trajectory(v.name, deadreckoning=True)
        if dr_path.exists():
            dr[v.name] = read_tum(dr_path)
            write_tum(
                out.trajectory(v.name, deadreckoning=True),
                dr[v.name],
                header=f"{header}\nvehicle {v.name}: dead reckoning (as in {source})",
            )
    write_map_csv(out.map_csv, lm)
    write_map_ply(out.map_ply, lm)
    meta = {"refine": source, "mode": "batch", "cvslam_version": __version__}
    write_result_mcap(
        out.result_mcap, tables, lm, pose_covariances={v.name: v.pose_cov for v in res.vehicles},
        deadreckoning=dr, metadata=meta,
    )  # fmt: skip


# --------------------------------------------------------------------------- stage


def _lm(
    problem: RefineProblem,
    settings: RefineSettings,
    progress: bool,
    warm: Any = None,
    warm_landmarks: bool = False,
    level: int = logging.INFO,
) -> tuple[graph.Graph, Any, float, float, int]:
    """Build the graph (its vehicle states started at `warm`, an earlier solution, when
    given; its landmarks too when `warm_landmarks`: a solution of the same landmarks) and
    solve it with Levenberg-Marquardt, with a progress bar; logged at `level`."""
    g = graph.build(problem, settings)
    if warm is not None:
        graph.warm_start(g, warm, warm_landmarks)
    log.log(
        level,
        "refine: %d keyframes, %d landmarks, %d observations; factors %s",
        sum(len(v.stamps_ns) for v in problem.vehicles),
        len(problem.landmark_id),
        len(problem.z_px),
        ", ".join(f"{k} {n}" for k, n in g.factors.items() if n),
    )
    bar = tqdm(
        total=settings.max_iterations, desc="refine (LM)", unit="it",
        disable=None if progress else True, leave=False,
    )  # fmt: skip

    start = time.perf_counter()

    def step(it: int, error: float) -> None:
        bar.update(1)
        bar.set_postfix(error=f"{error:.4g}")
        log.debug(
            "refine: iteration %d, error %.6g (%.1f s)", it, error, time.perf_counter() - start
        )

    with bar:
        values, e0, e1, iterations = graph.solve(g, settings, step)
    log.log(
        level,
        "refine: error %.6g -> %.6g in %d iterations (%.1f s)",
        e0, e1, iterations, time.perf_counter() - start,
    )  # fmt: skip
    return g, values, e0, e1, iterations


def _calibrated(
    problem: RefineProblem,
    settings: RefineSettings,
    progress: bool,
    c0_px: Any = None,
    warm: Any = None,
    warm_landmarks: bool = False,
) -> tuple[RefineProblem, tuple[graph.Graph, Any, float, float, int], right_cx.RightCx]:
    """The solution with each rig's right-camera u0 estimated on the way (`right_cx.py`;
    `problem`'s right cameras already moved by c0_px from the calibration): the corrected
    problem, its solution (graph, values, first and last error, iterations of every solve)
    and the estimate."""
    e_first: float | None = None  # the first solve's initial error
    iterations = 0

    def solve(p: RefineProblem, start: Any, same: bool) -> tuple[Any, Any, float]:
        nonlocal e_first, iterations
        sol = _lm(p, settings, progress, start, same, logging.DEBUG)
        if e_first is None:
            e_first = sol[2]
        iterations += sol[4]
        return sol, sol[1], sol[3]

    est = right_cx.estimate(problem, solve, settings.right_cx_sigma_px, c0_px, warm, warm_landmarks)
    g, values, _, e1, _ = est.solution
    log.info(
        "refine: right cameras' u0 corrected by %s px (%d solves, %d iterations); error %.6g",
        ", ".join(f"{c:+.3f} +- {sd:.3f}" for c, sd in zip(est.c_px, est.std_px, strict=True)),
        est.solves, iterations, e1,
    )  # fmt: skip
    assert e_first is not None  # estimate solves at least once
    return est.problem, (g, values, e_first, e1, iterations), est


def _marginals(
    problem: RefineProblem, g: graph.Graph, values: Any, settings: RefineSettings,
    e0: float, e1: float, iterations: int, progress: bool,
) -> RefineResult:  # fmt: skip
    log.info("refine: marginals")
    n = sum(len(v.stamps_ns) for v in problem.vehicles)
    bar = tqdm(
        total=n, desc="refine (marginals)", unit="var", disable=None if progress else True,
        leave=False,
    )  # fmt: skip
    start = time.perf_counter()
    with bar:
        res = graph.result(problem, g, values, settings, e0, e1, iterations, bar.update)
    log.info("refine: marginals in %.1f s", time.perf_counter() - start)
    return res


def reassociation_settings(cfg: Config) -> ReassociationSettings:
    rc = cfg.refine.reassociation
    return ReassociationSettings(
        rounds=rc.rounds, gate_px=rc.gate_px, gate_probability=rc.gate_probability,
        descriptor_ratio=rc.descriptor_ratio, max_descriptor_distance=rc.max_descriptor_distance,
        tracks=rc.tracks, min_track_keyframes=rc.min_track_keyframes,
        max_descriptors=rc.max_descriptors,
    )  # fmt: skip


def _reassociated(
    problem0: RefineProblem,
    features: dict[str, Any],
    observations: Any,
    source_map: LandmarkMap,
    archive: LandmarkArchive | None,
    settings: RefineSettings,
    rs: ReassociationSettings,
    progress: bool,
) -> RoundsResult:
    """The rounds of re-association and solutions (`rounds.py`) from the filter's problem."""
    kfs = [keyframe_features(features[v.name], v.stamps_ns) for v in problem0.vehicles]
    desc = true_id = None
    if archive is not None:
        row_of = {int(i): r for r, i in enumerate(archive.landmark_id)}
        rows = np.array([row_of.get(int(i), -1) for i in source_map.landmark_id], dtype=np.int64)
        if np.all(rows >= 0):
            desc, true_id = archive.descriptor[rows], archive.true_id[rows]
    if true_id is None:
        true_id = source_map.true_id
    points, base = reassociation_start(
        problem0.vehicles, kfs, observations, source_map.landmark_id, source_map.p_nav_m,
        desc, true_id, rs.max_descriptors,
    )  # fmt: skip
    next_id = int(source_map.landmark_id.max()) + 1 if len(source_map) else 0
    return run_rounds(
        problem0, kfs, points, base, settings, rs, next_id,
        lambda problem, warm: _lm(problem, settings, progress, warm), log.info,
    )  # fmt: skip


def run(
    cfg: Config,
    run_dir: Path,
    *,
    source: str | None = None,
    log_paths: Sequence[Path] = (),
    force: bool = False,
    progress: bool = False,
) -> RefineSummary:
    source = source or cfg.refine.source
    cfg = dataclasses.replace(cfg, refine=dataclasses.replace(cfg.refine, source=source))
    layout = RunLayout(run_dir)
    src = layout.fuse(source)
    out = layout.fuse(refined_name(source))
    if not src.has_trajectories():
        raise CvslamError(f"{src.path}: no fuse output (<vehicle>.tum); run `cvslam fuse` first")
    feature_files = layout.feature_files(f"run `cvslam extract LOG... -o {layout.root}` first")
    loaded = [load_features(p) for p in feature_files]
    features = {fs.vehicle: fs for fs, _ in loaded}
    metas = [m for _, m in loaded]
    vehicles = [v for v in src.vehicles() if v in features]
    src_files = _source_files(src, vehicles)
    cfg = dataclasses.replace(cfg, logs=with_run_bindings(cfg.logs, run_dir))
    logs_used = all_log_paths(list(log_paths) or layout.find_logs(metas), cfg.logs)
    require_logs(logs_used)
    rd = RunDir(run_dir)
    outputs = [out.map_csv, out.result_mcap, *(out.trajectory(v) for v in vehicles)]
    inputs_used = [*feature_files, *logs_used, *src_files]
    if src.map_npz.exists():  # the landmarks' descriptors, the map file's other fields
        inputs_used.append(src.map_npz)
        outputs.append(out.map_npz)
    plan = rd.plan(out.name, cfg, ("logs", "fuse", "refine"), inputs_used, outputs, force)
    if plan.action == "skip":
        log.info("refine: %s is up to date (same config and inputs); --force to redo it", out.path)
        return RefineSummary(out.path, True, source, {}, 0, 0, {}, 0, 0.0, 0.0, 0, 0.0, 0.0)
    check_writable(outputs)
    t_start = time.perf_counter()
    logs = open_logs(logs_used, cfg.logs)
    vin, truth = build_inputs(cfg, {v: features[v] for v in vehicles}, logs)
    tracks = {v: read_tum(src.trajectory(v)) for v in vehicles}
    observations = load_observations(src.observations)
    source_map = read_map_csv(src.map_csv)
    source_archive = load_map(src.map_npz) if src.map_npz.exists() else None
    if source_archive is None:
        log.info("refine: %s has no map file (map.npz): the refined run will have none", src.path)
    settings = settings_of(cfg, metas)
    try:
        problem = build_problem(
            vin, tracks, observations, source_map.landmark_id, source_map.p_nav_m,
            cfg.refine.every_nth,
        )  # fmt: skip
    except ValueError as exc:
        raise CvslamError(f"{src.path}: {exc}; run `cvslam fuse --force`") from None
    if not len(problem.z_px):
        raise CvslamError(
            f"{src.observations}: no landmark seen from two keyframes; nothing to refine"
        )
    rs = reassociation_settings(cfg)
    rounds: RoundsResult | None = None
    cx: right_cx.RightCx | None = None
    # the sparse factorisations gain from threads, unlike the filter's small matrices
    with threadpool_limits(limits=None):
        c0 = extract_right_cx(metas, problem)
        c_fuse = fuse_right_cx(rd.load(), source, problem)
        if np.any(c_fuse):  # start from the rigs the fuse run corrected
            problem, c0 = right_cx.moved(problem, c_fuse), c0 + c_fuse
            log.info(
                "refine: right cameras' u0 moved by %s px, as the fuse run's calibration pass "
                "corrected them%s", ", ".join(f"{c:+.3f}" for c in c_fuse),
                "" if settings.estimate_right_cx else " (refine.estimate_right_cx: not estimated)",
            )  # fmt: skip
        if rs.rounds == 0 and settings.estimate_right_cx:
            problem, (g, values, e0, e1, it), cx = _calibrated(problem, settings, progress, c0)
        elif rs.rounds == 0:
            g, values, e0, e1, it = _lm(problem, settings, progress)
        else:
            before = None  # the solution the right cameras were first corrected at
            if settings.estimate_right_cx:  # the rounds predict with the corrected cameras
                problem, before, cx = _calibrated(problem, settings, progress, c0)
            try:
                rounds = _reassociated(
                    problem, {v: features[v] for v in vehicles}, observations, source_map,
                    source_archive, settings, rs, progress,
                )  # fmt: skip
            except ValueError as exc:
                raise CvslamError(f"{layout.root}: {exc}; run `cvslam extract --force`") from None
            problem, g, values = rounds.problem, rounds.graph, rounds.values
            e0, e1, it = rounds.initial_error, rounds.final_error, rounds.iterations
            if before is not None and cx is not None:  # again, over the final observations
                problem, (g, values, _, e1, more), cx = _calibrated(
                    problem, settings, progress, cx.c_px, values, True
                )
                e0, it = before[2], it + before[4] + more
        try:
            res = _marginals(problem, g, values, settings, e0, e1, it, progress)
        except IndeterminateError as exc:
            raise CvslamError(
                f"{src.path}: refine: {exc}: a keyframe or landmark nothing constrains "
                "(refine.every_nth, refine.reassociation)"
            ) from None
    tables = {v.name: _pose_table(v.stamps_ns, v.T_nav_body) for v in res.vehicles}
    lm = refined_map(source_map, problem, res, None if rounds is None else rounds.true_id)
    archive = None
    if source_archive is not None:
        archive = refined_archive(
            source_archive, problem, res, *((rounds.descriptor, rounds.true_id) if rounds else ())
        )
    with atomic_dir(out.path) as tmp:
        _write(FuseFolder(tmp), src, tables, res, lm, archive, source)
    wall = time.perf_counter() - t_start
    summary = _summary(out.path, source, problem, res, tracks, tables, truth, settings, wall, cx)
    if rounds is not None:
        summary = dataclasses.replace(
            summary, rounds=rounds.rounds, removed_by_check=rounds.removed
        )
    rd.record(out.name, plan, outputs, _record(summary), wall)
    return summary


def _summary(
    out_dir: Path,
    source: str,
    problem: RefineProblem,
    res: RefineResult,
    tracks: dict[str, PoseTable],
    tables: dict[str, PoseTable],
    truth: dict[str, PoseTable],
    settings: RefineSettings,
    wall: float,
    cx: right_cx.RightCx | None,
) -> RefineSummary:
    vehicles = {}
    n = len(problem.vehicles)
    c_px = np.full(n, np.nan) if cx is None else cx.c_px
    c_std_px = np.full(n, np.nan) if cx is None else cx.std_px
    for i, v in enumerate(problem.vehicles):
        src = tracks[v.name]
        at_kf = np.isin(src.stamps_ns, v.stamps_ns)
        src_kf = PoseTable(src.stamps_ns[at_kf], src.p_nav_m[at_kf], src.q_nav_body_xyzw[at_kf])
        J = v.model.pose_jacobian(v.x_first)
        prior = J @ v.P_first @ J.T
        vehicles[v.name] = VehicleRefine(
            keyframes=len(v.stamps_ns),
            model=v.model.kind,
            rmse_source_m=_rmse(src_kf, truth.get(v.name)),
            rmse_m=_rmse(tables[v.name], truth.get(v.name)),
            prior_sigma_position_m=float(np.sqrt(np.trace(prior[:3, :3]))),
            prior_sigma_attitude_rad=float(np.sqrt(np.trace(prior[3:, 3:]))),
            right_cx_px=float(c_px[i]),
            right_cx_std_px=float(c_std_px[i]),
        )
    return RefineSummary(
        out_dir, False, source, vehicles, len(problem.landmark_id), len(problem.z_px),
        res.factors, res.iterations, res.initial_error, res.final_error, res.outliers,
        settings.pixel_sigma_px, wall,
    )  # fmt: skip


def _record(s: RefineSummary) -> dict[str, Any]:
    """The refine run's summary in run.yaml (the gauge: the prior on each first keyframe)."""
    return {
        "source": s.source,
        "gauge": "prior on each vehicle's first keyframe: the filter's initial state "
        "predicted to it (fuse.initial)",
        "vehicles": {
            k: {kk: round(float(x), 6) if isinstance(x, float) else x for kk, x in vars(v).items()}
            for k, v in s.vehicles.items()
        },
        "landmarks": s.landmarks,
        "observations": s.observations,
        "factors": s.factors,
        "iterations": s.iterations,
        "initial_error": round(s.initial_error, 3),
        "final_error": round(s.final_error, 3),
        "outliers": s.outliers,
        "pixel_sigma_px": s.pixel_sigma_px,
        "reassociation": {
            "rounds": [
                {k: round(x, 6) if isinstance(x, float) else x for k, x in vars(r).items()}
                for r in s.rounds
            ],
            "removed_by_check": s.removed_by_check,
        },
    }
