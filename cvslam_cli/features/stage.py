"""`cvslam extract`: every stereo frame of every vehicle -> keypoints, stereo matches and
triangulated points, in the feature format (docs/feature_format.md).

Per frame: adaptive SIFT on both images (`sift.py`), keypoints undistorted, stereo-
constrained matching (`matching.py`, eq. 20-34), triangulation from both projection
matrices with a covariance from the keypoint localisation noise (the inverse observation
model, `geometry/stereo.py`), rejecting points behind the cameras or beyond the maximum
range. Frames are processed in parallel worker processes (`--workers`) and collected in
time order. Outputs, written to temporary names and renamed when complete:

    <run>/features/<vehicle>.npz        the FeatureSet
    <run>/features/<vehicle>_stats.csv  one row per frame (counts, adaptive parameters,
                                        candidates per keypoint, time per step)
    <run>/run.yaml                      the stage record (config, input checksums)
"""

from __future__ import annotations

import csv
import io
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from cvslam_cli import __version__
from cvslam_cli.config import Config, ExtractConfig
from cvslam_cli.errors import CvslamError, LogError
from cvslam_cli.features.disparity_offset import (
    MIN_DISPARITY_SPREAD,
    apply_disparity_offset,
    estimate_disparity_offset,
)
from cvslam_cli.features.matching import match_stereo
from cvslam_cli.features.sift import Keypoints, detect_and_describe, to_grey_u8
from cvslam_cli.features.windows import auto_z_min_m, undistort_keypoints
from cvslam_cli.geometry.camera import StereoRig, rig_calibration
from cvslam_cli.geometry.stereo import triangulate_matches
from cvslam_cli.io.atomic import check_writable, write_text_atomic
from cvslam_cli.io.features_file import save_features
from cvslam_cli.io.logs import LogSet, all_log_paths, open_logs
from cvslam_cli.io.run_layout import EXTRACT_STAGE, RunLayout
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.parallel import STATE, ordered_map
from cvslam_cli.records.features import FeatureSet, FeatureSetBuilder
from cvslam_cli.records.log import StereoFrame

log = logging.getLogger("cvslam")

STATS_COLUMNS = (
    "stamp_ns",
    "kp_left",
    "kp_right",
    "layers_left",
    "layers_right",
    "contrast_left",
    "contrast_right",
    "dog_rms_left",
    "dog_rms_right",
    "retried_left",
    "retried_right",
    "candidates_per_kp",
    "matches",
    "points",
    "t_detect_s",
    "t_describe_s",
    "t_match_s",
    "t_triangulate_s",
    "t_total_s",
)


@dataclass(frozen=True)
class VehicleExtract:
    frames: int
    empty_frames: int
    unpaired_left: int
    unpaired_right: int
    keypoints_per_frame: float
    matches_per_frame: float
    candidates_per_keypoint: float
    wall_s: float


@dataclass(frozen=True)
class ExtractSummary:
    run_dir: Path
    skipped: bool
    vehicles: dict[str, VehicleExtract]


def stereo_limits(rig: StereoRig, cfg: ExtractConfig) -> tuple[float, float]:
    """(z_min_m, max_range_m) with the automatic defaults resolved from the rig."""
    max_range = cfg.stereo.max_range_m or 400.0 * rig.baseline_m
    return auto_z_min_m(rig, cfg.stereo.z_min_m), max_range


# ----------------------------------------------------------------------------- one frame


def _side(kp: Keypoints, uv_px: np.ndarray) -> dict[str, np.ndarray]:
    return {
        "uv_raw_px": kp.uv_raw_px,
        "uv_px": uv_px,
        "size_px": kp.size_px,
        "angle_deg": kp.angle_deg,
        "response": kp.response,
        "octave": kp.octave,
        "desc": kp.desc,
    }


def process_frame(
    left_img: np.ndarray, right_img: np.ndarray, rig: StereoRig, cfg: ExtractConfig
) -> tuple[dict, dict, dict, dict[str, Any]]:
    """(left keypoints, right keypoints, matches, stats row) of one stereo frame."""
    t0 = time.perf_counter()
    kl, sl = detect_and_describe(left_img, cfg.sift, cfg.adaptive)
    kr, sr = detect_and_describe(right_img, cfg.sift, cfg.adaptive)
    uvl = undistort_keypoints(rig.left, kl.uv_raw_px)
    uvr = undistort_keypoints(rig.right, kr.uv_raw_px)
    t1 = time.perf_counter()
    m = match_stereo(uvl, kl.desc, uvr, kr.desc, rig, cfg.stereo)
    t2 = time.perf_counter()
    _, max_range = stereo_limits(rig, cfg)
    p_cam, cov, keep = triangulate_matches(
        rig, uvl[m.left], uvr[m.right], max_range, cfg.stereo.pixel_sigma_px
    )
    t3 = time.perf_counter()
    matches = {
        "left": m.left[keep],
        "right": m.right[keep],
        "disparity_px": m.disparity_px[keep],
        "distance": m.distance[keep],
        "ratio": m.ratio[keep],
        "p_cam_m": p_cam[keep],
        "cov_cam_m2": cov,
        "landmark_id": np.full(int(keep.sum()), -1, dtype=np.int64),
    }
    stats = {
        "kp_left": len(kl.uv_raw_px),
        "kp_right": len(kr.uv_raw_px),
        "layers_left": sl.n_octave_layers,
        "layers_right": sr.n_octave_layers,
        "contrast_left": round(sl.contrast_threshold, 6),
        "contrast_right": round(sr.contrast_threshold, 6),
        "dog_rms_left": round(sl.dog_rms, 6),
        "dog_rms_right": round(sr.dog_rms, 6),
        "retried_left": int(sl.retried),
        "retried_right": int(sr.retried),
        "candidates_per_kp": round(m.candidates_examined / max(1, m.n_left), 3),
        "matches": int(m.left.size),
        "points": int(keep.sum()),
        "t_detect_s": round(sl.detect_s + sr.detect_s, 5),
        "t_describe_s": round(sl.describe_s + sr.describe_s, 5),
        "t_match_s": round(t2 - t1, 5),
        "t_triangulate_s": round(t3 - t2, 5),
        "t_total_s": round(t3 - t0, 5),
    }
    return _side(kl, uvl), _side(kr, uvr), matches, stats


# ----------------------------------------------------------------------------- workers


def _job(args: tuple[str, int, np.ndarray, np.ndarray]) -> tuple[str, int, tuple]:
    vehicle, stamp, left, right = args
    return vehicle, stamp, process_frame(left, right, STATE["rigs"][vehicle], STATE["cfg"])


def _describe_job(args: tuple[str, int, np.ndarray, np.ndarray]) -> str:
    return f"the {args[0]} frame at stamp {args[1]} ns"


def _frames(logs: LogSet, vehicles: list[str]) -> Iterator[tuple[str, int, np.ndarray, np.ndarray]]:
    for rec in logs.records(vehicles=vehicles, roles=("left_image", "right_image")):
        if isinstance(rec, StereoFrame):
            yield rec.vehicle, rec.stamp_ns, to_grey_u8(rec.left.image), to_grey_u8(rec.right.image)


# ----------------------------------------------------------------------------- stage


def _csv_text(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=STATS_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def _stereo_vehicles(logs: LogSet) -> list[str]:
    vehicles = [v for v, vt in logs.vehicles.items() if vt.has_stereo]
    if not vehicles:
        raise CvslamError(
            f"{logs.names}: no vehicle with stereo images (left and right image "
            "topics); see logs.vehicles in the config"
        )
    return vehicles


def _log_stereo_limits(rigs: dict[str, StereoRig], cfg: ExtractConfig) -> None:
    for v, rig in rigs.items():
        z_min, max_range = stereo_limits(rig, cfg)
        log.debug(
            "extract %s: baseline %.3f m, %s, z_min %.2f m (HD_max %.1f px), max range %.0f m",
            v,
            rig.baseline_m,
            "rectified" if rig.rectified else "unrectified",
            z_min,
            rig.left.fx * rig.baseline_m / z_min,
            max_range,
        )


def _log_detector(cfg: ExtractConfig, workers: int, scheduler: str | None) -> None:
    """-v: the detector chosen and where the frames are worked on."""
    a, sift = cfg.adaptive, cfg.sift
    if a.enabled:
        detector = (
            f"adaptive SIFT ({a.layers_min}-{a.layers_max} layers per octave, contrast "
            f"{a.contrast_min:g}-{a.contrast_max:g}, {a.features_min}-{a.features_max} "
            "keypoints per image; extract.adaptive)"
        )
    else:
        detector = (
            f"fixed SIFT ({sift.n_octave_layers} layers per octave, contrast "
            f"{sift.contrast_threshold:g}; extract.adaptive.enabled is false)"
        )
    where = f"the Dask cluster at {scheduler}" if scheduler else f"{workers} worker process(es)"
    log.debug(
        "extract: %s, distance ratio %g, left-right check %s; frames on %s",
        detector,
        cfg.stereo.dist_ratio,
        "on" if cfg.stereo.left_right_check else "off",
        where,
    )


@dataclass(frozen=True, eq=False)
class _Extracted:
    """Per vehicle: the feature set being built, one stats row per frame, and the seconds
    its frames took (summed over the workers); the stage's wall time."""

    builders: dict[str, FeatureSetBuilder]
    rows: dict[str, list[dict[str, Any]]]
    frame_s: dict[str, float]
    wall_s: float


def _extract(
    logs: LogSet,
    rigs: dict[str, StereoRig],
    cfg: ExtractConfig,
    workers: int,
    progress: bool,
    scheduler: str | None = None,
) -> _Extracted:
    """Every stereo frame of the vehicles of `rigs`, in parallel (worker processes, or
    chunks of frames on the Dask cluster at `scheduler`), collected in time order."""
    vehicles = list(rigs)
    builders = {v: FeatureSetBuilder(v, rig_calibration(rigs[v])) for v in vehicles}
    rows: dict[str, list[dict[str, Any]]] = {v: [] for v in vehicles}
    started = {v: 0.0 for v in vehicles}
    total = sum(logs.vehicles[v].infos["left_image"].message_count for v in vehicles)
    t_start = time.perf_counter()
    with tqdm(
        total=total, desc="extract", unit="pair", disable=None if progress else True, leave=False
    ) as bar:
        state = {"rigs": rigs, "cfg": cfg}
        if scheduler:
            from cvslam_cli.cluster import ordered_chunk_map

            results = ordered_chunk_map(
                _job, _frames(logs, vehicles), scheduler=scheduler, state=state
            )
        else:
            results = ordered_map(
                _job, _frames(logs, vehicles), workers=workers, state=state, describe=_describe_job
            )
        for vehicle, stamp, (left, right, matches, stats) in results:
            builders[vehicle].add_frame(stamp, left, right, matches)
            rows[vehicle].append({"stamp_ns": stamp, **stats})
            started[vehicle] += stats["t_total_s"]
            bar.update(1)
    return _Extracted(builders, rows, started, time.perf_counter() - t_start)


def _calibrated(
    vehicle: str,
    fs: FeatureSet,
    rig: StereoRig,
    cfg: ExtractConfig,
    rows: list[dict[str, Any]],
) -> tuple[FeatureSet, dict[str, Any]]:
    """`fs` with its rig's disparity offset estimated and, when the frames determine it,
    corrected (`disparity_offset.py`); the stats rows' point counts follow. The estimate for
    the feature file's provenance."""
    est = estimate_disparity_offset(fs, rig)
    if est is None:
        log.info(
            "extract %s: disparity offset not estimated (%s)",
            vehicle,
            "the rig is not rectified" if not rig.rectified else "too few re-found points",
        )
        return fs, {"applied_px": 0.0}
    record = {"applied_px": 0.0, **asdict(est)}
    if not est.determined:
        log.info(
            "extract %s: disparity offset not determined (the points' disparities spread "
            "%.2f of their mean, below %.2f: an offset and a scale look alike); the rig is "
            "left as calibrated",
            vehicle,
            est.disparity_spread,
            MIN_DISPARITY_SPREAD,
        )
        return fs, record
    fs, per_frame = apply_disparity_offset(
        fs, est.offset_px, stereo_limits(rig, cfg)[1], cfg.stereo.pixel_sigma_px
    )
    for row, n in zip(rows, per_frame, strict=True):
        row["points"] = int(n)
    log.info(
        "extract %s: disparity offset %+.3f +- %.3f px (%d frame pairs, %d points): stereo "
        "depth at 25 m was %+.1f %% off; corrected (right camera cx %.3f -> %.3f px)",
        vehicle,
        est.offset_px,
        est.sigma_px,
        est.pairs,
        est.points,
        100 * est.depth_error(25.0, rig),
        rig.right.cx,
        fs.rig.K[1, 0, 2],
    )
    return fs, record | {"applied_px": est.offset_px}


def _vehicle_extract(
    r: list[dict[str, Any]], unpaired: tuple[int, int], frame_s: float
) -> VehicleExtract:
    """The summary of one vehicle's stats rows `r`; `unpaired`: left and right images the
    logs had no partner for."""
    n = max(1, len(r))
    return VehicleExtract(
        frames=len(r),
        empty_frames=sum(1 for x in r if x["kp_left"] == 0 or x["kp_right"] == 0),
        unpaired_left=unpaired[0],
        unpaired_right=unpaired[1],
        keypoints_per_frame=sum(x["kp_left"] + x["kp_right"] for x in r) / (2 * n),
        matches_per_frame=sum(x["points"] for x in r) / n,
        candidates_per_keypoint=sum(x["candidates_per_kp"] for x in r) / n,
        wall_s=frame_s,
    )


def run(
    cfg: Config,
    log_paths: Sequence[Path],
    run_dir: Path,
    *,
    workers: int = 2,
    force: bool = False,
    progress: bool = False,
    scheduler: str | None = None,
) -> ExtractSummary:
    """Extract every stereo frame of `log_paths` into `run_dir`; `scheduler`: the address of
    a Dask scheduler to spread the frames over instead of `workers` local processes (the
    output is the same, byte for byte)."""
    rd = RunDir(run_dir)
    layout = RunLayout(run_dir)
    logs = open_logs(log_paths, cfg.logs)
    vehicles = _stereo_vehicles(logs)
    outputs = [p for v in vehicles for p in (layout.feature_file(v), layout.feature_stats(v))]
    inputs = all_log_paths(log_paths, cfg.logs)
    plan = rd.plan(EXTRACT_STAGE, cfg, ("logs", "extract"), inputs, outputs, force)
    if plan.action == "skip":
        log.info("extract: %s is up to date (same config and inputs); --force to redo it", run_dir)
        return ExtractSummary(run_dir, True, {})
    check_writable(outputs)  # before the work: a read-only folder, a name too long
    rigs = {v: logs.rig(v) for v in vehicles}
    _log_stereo_limits(rigs, cfg.extract)
    _log_detector(cfg.extract, workers, scheduler)
    done = _extract(logs, rigs, cfg.extract, workers, progress, scheduler)
    for v in vehicles:
        if not done.rows[v]:
            vs = logs.stats[v]
            raise LogError(
                f"{logs.names}: vehicle {v}: no stereo pairs (no left and right image within "
                f"logs.stereo_pair_tolerance_ms = {cfg.logs.stereo_pair_tolerance_ms:g} ms of "
                f"each other; {vs.unpaired_left} left and {vs.unpaired_right} right images "
                "unpaired); nothing written"
            )
    summaries: dict[str, VehicleExtract] = {}
    for v in vehicles:
        meta = {
            "producer": f"cvslam extract {__version__}",
            "vehicle": v,
            "inputs": layout.relative_inputs(plan.inputs),
            "config": plan.sections["extract"],
        }
        fs = done.builders[v].build()
        if cfg.extract.stereo.calibrate_disparity_offset:
            fs, meta["disparity_offset"] = _calibrated(v, fs, rigs[v], cfg.extract, done.rows[v])
        save_features(fs, layout.feature_file(v), meta)
        write_text_atomic(layout.feature_stats(v), _csv_text(done.rows[v]))
        vs = logs.stats[v]
        unpaired = (vs.unpaired_left, vs.unpaired_right)
        summaries[v] = _vehicle_extract(done.rows[v], unpaired, done.frame_s[v])
    rd.record(
        EXTRACT_STAGE,
        plan,
        outputs,
        {"vehicles": {v: asdict(s) for v, s in summaries.items()}, "workers": workers},
        done.wall_s,
    )
    return ExtractSummary(run_dir, False, summaries)
