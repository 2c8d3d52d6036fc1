"""`cvslam mosaic`: every n-th left image of every vehicle projected on the ground with its
pose, blended into one mosaic per vehicle and one of all vehicles (docs/mosaic.md).

Inputs: the frames of `<run>/features/<vehicle>.npz` (their stamps and the logs they came
from), the trajectories and landmark map of `<run>/<fuse_dir>/`, the images from the logs.
1. Ground: planes fitted to the mapped landmarks (`ground.py`).
2. Poses of the frames from the source (fused, dead reckoning, or the logs' ground truth),
   the camera pose T_nav_cam = T_nav_body T_body_cam; each frame's footprint on the ground
   (`project.py`), the GSD (configured, or the images' own median ground resolution), one
   north-up canvas over all footprints; each vehicle's mosaic is a sub-rectangle of it, so
   every warped image is fed to its vehicle's blender and the merged one unchanged.
3. One pass over the logs: each selected left image is warped and fed (`blend.py`).
4. Written to `<run>/mosaic*/` as a whole folder, atomically (`io/atomic.py`): `<vehicle>.png`,
   `all.png` (BGRA, alpha 0 where no image fell) with world files and their CRS, the same
   as GeoTIFFs (`.tif`), `*_overlay.png` with the trajectories, landmarks and a scale bar
   (and world files). The map is the nav frame's east/north (a local engineering CRS) or,
   with `geo.origin`, UTM (`geometry/georef.py`). The summary in run.yaml gives the map's
   CRS, images used, size, covered area per mosaic, and, for a simulated run, the alignment
   with the true ground texture.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from cvslam_cli.config import Config, MosaicConfig
from cvslam_cli.errors import CvslamError
from cvslam_cli.geometry.camera import CameraModel
from cvslam_cli.geometry.georef import MapPlacement, local_placement, scale_bar_m, utm_placement
from cvslam_cli.geometry.rotations import interpolate_poses, quat_xyzw_to_matrix
from cvslam_cli.io.atomic import atomic_dir, check_writable
from cvslam_cli.io.features_file import feature_frame_index
from cvslam_cli.io.fuse_files import read_map_csv
from cvslam_cli.io.logs import (
    LogSet,
    all_log_paths,
    ground_truth_tables,
    open_logs,
    require_logs,
    with_run_bindings,
)
from cvslam_cli.io.mosaic_files import (
    load_true_ground,
    write_crs_sidecar,
    write_geotiff_atomic,
    write_png_atomic,
    write_world_file,
)
from cvslam_cli.io.run_layout import (
    MERGED_MOSAIC,
    FuseFolder,
    MosaicFolder,
    RunLayout,
    SimLayout,
    mosaic_name,
)
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.mosaic.blend import Blended, Compositor
from cvslam_cli.mosaic.compare import align_to_reference, resample_reference
from cvslam_cli.mosaic.ground import GroundFitError, GroundModel, fit_ground
from cvslam_cli.mosaic.project import (
    CanvasGrid,
    ViewLimits,
    footprint_box,
    image_gsd_m,
    warp_to_canvas,
)
from cvslam_cli.records.landmarks import LandmarkMap
from cvslam_cli.records.log import StereoFrame
from cvslam_cli.records.poses import PoseTable

log = logging.getLogger("cvslam")

# BGR colours of the vehicles' tracks in the overlays (matplotlib's tab10)
PALETTE = ((180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148))


@dataclass(frozen=True)
class MosaicInfo:
    """One written mosaic: images fed, size (cols, rows) after cropping, covered area, and
    its alignment with the simulator's true ground (None without one)."""

    images: int
    width_px: int
    height_px: int
    covered_m2: float
    truth: dict[str, Any] | None


@dataclass(frozen=True)
class MosaicSummary:
    run_dir: Path
    out_dir: Path
    skipped: bool
    source: str
    gsd_m: float = float("nan")
    mosaics: dict[str, MosaicInfo] = dataclasses.field(default_factory=dict)
    union_coverage: float = float("nan")
    ground_local_regions: int = 0
    images_per_s: float = float("nan")
    wall_s: float = float("nan")


@dataclass(frozen=True, eq=False)
class _Frame:
    vehicle: str
    stamp_ns: int
    T_nav_cam: np.ndarray
    box_ne: np.ndarray


@dataclass(frozen=True, eq=False)
class _Scene:
    """What warping an image onto the canvas needs: the ground, each vehicle's left camera
    and view limits, the merged canvas and each vehicle's part of it (row, col, rows, cols)."""

    ground: GroundModel
    cams: dict[str, CameraModel]
    limits: dict[str, ViewLimits]
    grid: CanvasGrid
    sub_rois: dict[str, tuple[int, int, int, int]]


# --------------------------------------------------------------------------- inputs


def _landmarks(table: LandmarkMap, max_std_m: float) -> np.ndarray:
    ok = ~(table.max_std_m > max_std_m)  # NaN std (unknown) is kept
    return table.p_nav_m[ok]


def _true_ground(run_dir: Path, logs_used: Sequence[Path]) -> Any:
    """The simulator's world, from `<run>/truth/` or the `truth/` beside the logs (a
    simulator output directory), or None for real data."""
    for folder in (run_dir, *(p.parent for p in logs_used)):
        world = load_true_ground(SimLayout(folder).world)
        if world is not None:
            return world
    return None


# --------------------------------------------------------------------------- geometry


def _two_digits(x: float) -> float:
    """x rounded up to two significant digits."""
    e = np.floor(np.log10(x)) - 1
    return float(np.ceil(x / 10**e - 1e-9) * 10**e)


def _union(boxes: Sequence[np.ndarray]) -> np.ndarray:
    b = np.asarray(boxes)
    return np.r_[b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()]


def _camera_height(ground: GroundModel, c: np.ndarray) -> float:
    return float(ground.z_at(c[0], c[1]) - c[2])


def _limits(cfg: MosaicConfig, height_m: float) -> ViewLimits:
    """What a camera `height_m` above the ground contributes (range default: 20 x height)."""
    rng = cfg.max_range_m or 20.0 * max(height_m, 0.1)
    return ViewLimits(rng, cfg.min_depression_deg, cfg.border_px)


# --------------------------------------------------------------------------- overlay


def _overlay(
    blended: Blended,
    grid: CanvasGrid,
    tracks: dict[str, np.ndarray],
    landmarks: dict[str, np.ndarray],
) -> np.ndarray:
    """The mosaic (BGR, no-data grey) with tracks (lines) and landmarks (dots) drawn."""
    img = blended.image
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    bgr[~blended.mask] = (64, 64, 64)
    sub = grid.sub((*blended.offset_rc, *blended.mask.shape))
    scale = 16  # fixed-point drawing (4 fractional bits)
    for i, (v, pts) in enumerate(tracks.items()):
        colour = PALETTE[i % len(PALETTE)]
        lm = landmarks.get(v, np.zeros((0, 3)))
        r, c = sub.pixel_of(lm[:, 0], lm[:, 1])
        for rr, cc in zip(r, c, strict=True):
            cv2.circle(
                bgr, (int(cc * scale), int(rr * scale)), 2 * scale, colour, 1, cv2.LINE_AA, 4
            )
        r, c = sub.pixel_of(pts[:, 0], pts[:, 1])
        poly = np.round(np.c_[c, r] * scale).astype(np.int32)
        cv2.polylines(bgr, [poly], False, colour, max(2, bgr.shape[1] // 800), cv2.LINE_AA, 4)
        fs = _font_scale(bgr)
        org = (int(12 * fs), int(32 * fs * (i + 1)))
        thick = max(1, round(2 * fs))
        cv2.putText(bgr, v, org, cv2.FONT_HERSHEY_SIMPLEX, fs, colour, thick, cv2.LINE_AA)
    _scale_bar(bgr, grid.gsd_m)
    return bgr


def _font_scale(bgr: np.ndarray) -> float:
    """OpenCV font scale of the overlay's text: readable at any mosaic size."""
    return max(0.6, bgr.shape[1] / 1600.0)


def _scale_bar(bgr: np.ndarray, gsd_m: float) -> None:
    """A scale bar (a round length, about a quarter of the width) drawn in the bottom left
    corner of `bgr` in place: white on a black outline, labelled in metres."""
    h, w = bgr.shape[:2]
    length_m = scale_bar_m(w * gsd_m)
    length_px = round(length_m / gsd_m)
    fs = _font_scale(bgr)
    thick = max(1, round(2 * fs))
    bar_h = max(4, round(8 * fs))
    x0, y1 = round(12 * fs), h - round(12 * fs)
    label = f"{length_m:g} m"
    (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, fs, thick)
    org = (x0 + max(0, (length_px - tw) // 2), y1 - bar_h - round(8 * fs))
    for colour, grow in (((0, 0, 0), 2), ((255, 255, 255), 0)):
        cv2.rectangle(
            bgr, (x0 - grow, y1 - bar_h - grow), (x0 + length_px + grow, y1 + grow), colour, -1
        )
        cv2.putText(
            bgr, label, org, cv2.FONT_HERSHEY_SIMPLEX, fs, colour, thick + grow, cv2.LINE_AA
        )


# --------------------------------------------------------------------------- stage


def _with_overrides(cfg: Config, source: str | None, gsd_m: float | None) -> Config:
    m = cfg.mosaic
    if source is not None:
        m = dataclasses.replace(m, source=source)  # type: ignore[arg-type]
    if gsd_m is not None:
        if not (math.isfinite(gsd_m) and gsd_m > 0):
            raise CvslamError(
                f"--gsd: expected a finite number of metres per pixel > 0, got {gsd_m}"
            )
        m = dataclasses.replace(m, gsd_m=gsd_m)
    return dataclasses.replace(cfg, mosaic=m)


def _fuse_inputs(fuse: FuseFolder, vehicles: Sequence[str], source: str) -> dict[str, Path]:
    """The trajectory files the poses come from ({} for the ground truth), checking that the
    fuse run wrote its landmark map."""
    if not fuse.map_csv.exists():
        raise CvslamError(f"{fuse.map_csv}: landmark map not found; run `cvslam fuse` first")
    if source == "groundtruth":
        return {}
    return fuse.trajectories(vehicles, deadreckoning=source == "deadreckoning")


def _open_logs(cfg: Config, logs_used: Sequence[Path], vehicles: Sequence[str]) -> LogSet:
    logs = open_logs(logs_used, cfg.logs)
    missing = [v for v in vehicles if v not in logs.vehicles]
    if missing:
        raise CvslamError(f"{logs.names}: no vehicle {missing[0]!r} (it has features)")
    return logs


def _poses(
    logs: LogSet, vehicles: Sequence[str], source: str, traj_files: dict[str, Path]
) -> dict[str, PoseTable]:
    """The body poses of each vehicle from the mosaic's source."""
    if source == "groundtruth":
        return ground_truth_tables(logs, vehicles)
    return {v: read_tum(p) for v, p in traj_files.items()}


def _ground(
    table: LandmarkMap,
    tables: dict[str, PoseTable],
    cams: dict[str, CameraModel],
    cfg: MosaicConfig,
    map_path: Path,
) -> GroundModel:
    """The ground fitted to the mapped landmarks, below the cameras' positions."""
    camera_positions = np.vstack(
        [
            tables[v].p_nav_m
            + quat_xyzw_to_matrix(tables[v].q_nav_body_xyzw) @ cams[v].T_body_cam[:3, 3]
            for v in cams
        ]
    )
    try:
        return fit_ground(
            _landmarks(table, cfg.ground.max_landmark_std_m), camera_positions, cfg.ground
        )
    except GroundFitError as exc:
        raise CvslamError(f"{map_path}: no ground surface from the landmarks: {exc}") from None


def _frames(
    frame_stamps_ns: dict[str, np.ndarray],
    tables: dict[str, PoseTable],
    cams: dict[str, CameraModel],
    ground: GroundModel,
    cfg: MosaicConfig,
) -> tuple[list[_Frame], dict[str, ViewLimits], list[float]]:
    """(every n-th frame with a pose and a footprint on the ground, each vehicle's view
    limits, the ground resolution of about 100 frames per vehicle)."""
    frames: list[_Frame] = []
    limits: dict[str, ViewLimits] = {}
    gsds: list[float] = []
    for v, cam in cams.items():
        at = frame_stamps_ns[v][:: cfg.every_nth]
        tab = tables[v]
        p, R, ok = interpolate_poses(tab.stamps_ns, tab.p_nav_m, tab.q_nav_body_xyzw, at)
        T = np.zeros((len(at), 4, 4))
        T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, p, 1.0
        T_nav_cam = T @ cam.T_body_cam
        heights = [_camera_height(ground, t[:3, 3]) for t in T_nav_cam[ok]]
        if not heights:
            log.warning("mosaic: %s: no pose at any of its frames; no images used", v)
            continue
        limits[v] = _limits(cfg, float(np.median(heights)))
        step = max(1, int(ok.sum()) // 100)
        for k in np.flatnonzero(ok):
            box = footprint_box(cam, T_nav_cam[k], ground, limits[v])
            if box is not None:
                frames.append(_Frame(v, int(at[k]), T_nav_cam[k], box))
            if k % step == 0:
                gsds.append(image_gsd_m(cam, T_nav_cam[k], ground, limits[v]))
    return frames, limits, gsds


def _canvas(
    frames: list[_Frame], gsds: list[float], cfg: MosaicConfig, run_dir: Path
) -> tuple[CanvasGrid, float]:
    """(the north-up grid over every footprint, its GSD): the configured GSD, else the
    images' own but no finer than auto_max_mpx allows; coarser above max_canvas_mpx."""
    if not frames:
        raise CvslamError(f"{run_dir}: no frame sees the ground; nothing to mosaic")
    finite = [g for g in gsds if np.isfinite(g)]
    if not cfg.gsd_m and not finite:
        raise CvslamError(f"{run_dir}: no ground resolution from the images; give --gsd")
    box_all = _union([f.box_ne for f in frames])
    gsd = cfg.gsd_m
    if not gsd:  # the images' own resolution, but no finer than auto_max_mpx allows
        area = float((box_all[2] - box_all[0]) * (box_all[3] - box_all[1]))
        gsd = _two_digits(max(float(np.median(finite)), np.sqrt(area / (cfg.auto_max_mpx * 1e6))))
    grid = CanvasGrid.covering(box_all, gsd)
    if grid.megapixels > cfg.max_canvas_mpx:
        coarser = _two_digits(gsd * np.sqrt(grid.megapixels / cfg.max_canvas_mpx))
        log.warning(
            "mosaic: %.0f x %.0f m at %.3g m/px would be %.0f Mpx (mosaic.max_canvas_mpx %.0f); "
            "using %.3g m/px",
            box_all[2] - box_all[0],
            box_all[3] - box_all[1],
            gsd,
            grid.megapixels,
            cfg.max_canvas_mpx,
            coarser,
        )
        gsd = coarser
        grid = CanvasGrid.covering(box_all, gsd)
    return grid, gsd


def _vehicle_rois(
    frames: list[_Frame], grid: CanvasGrid, cfg: MosaicConfig
) -> dict[str, tuple[int, int, int, int]]:
    """Each vehicle's canvas: the part of the merged one its frames cover, its origin on the
    multiples of the blender's unit so that an image prepared once is added to both."""
    unit = 1 << cfg.multiband_bands if cfg.blend == "multiband" else 1
    sub_rois = {}
    for v in sorted({f.vehicle for f in frames}):  # sorted: not in hash order
        roi = grid.roi_of(_union([f.box_ne for f in frames if f.vehicle == v]))
        assert roi is not None
        r0, c0 = roi[0] // unit * unit, roi[1] // unit * unit
        sub_rois[v] = (r0, c0, roi[2] + roi[0] - r0, roi[3] + roi[1] - c0)
    return sub_rois


def _compositors(
    sub_rois: dict[str, tuple[int, int, int, int]], grid: CanvasGrid, cfg: MosaicConfig
) -> tuple[dict[str, Compositor], Compositor | None]:
    """(one blender per vehicle, one for the merged mosaic when there are several)."""

    def compositor(shape: tuple[int, int]) -> Compositor:
        return Compositor(
            shape, cfg.blend, sharpness=cfg.feather_sharpness, bands=cfg.multiband_bands
        )

    comps = {v: compositor(roi[2:]) for v, roi in sub_rois.items()}
    return comps, compositor(grid.shape) if len(comps) > 1 else None


def _feed_images(
    logs: LogSet,
    frames: list[_Frame],
    scene: _Scene,
    comps: dict[str, Compositor],
    merged: Compositor | None,
    progress: bool,
) -> tuple[int, float]:
    """One pass over the logs: each selected left image warped onto the canvas and fed to
    its vehicle's blender and the merged one; (images fed, seconds it took)."""
    wanted = {(f.vehicle, f.stamp_ns): f for f in frames}
    fed = 0
    t_images = time.perf_counter()
    with tqdm(
        total=len(frames),
        desc="mosaic",
        unit="img",
        disable=None if progress else True,
        leave=False,
    ) as bar:
        for rec in logs.records(vehicles=sorted(comps), roles=("left_image", "right_image")):
            if not isinstance(rec, StereoFrame):
                continue
            f = wanted.pop((rec.vehicle, rec.stamp_ns), None)
            if f is None:
                continue
            roi = scene.grid.roi_of(f.box_ne)
            if roi is not None:
                img = rec.left.image
                if img.dtype != np.uint8:  # 16-bit: scale to 8 bits
                    img = cv2.convertScaleAbs(img, alpha=255.0 / max(1.0, float(img.max())))
                patch, mask = warp_to_canvas(
                    img,
                    scene.cams[f.vehicle],
                    f.T_nav_cam,
                    scene.ground,
                    scene.grid,
                    roi,
                    scene.limits[f.vehicle],
                )
                r0, c0 = roi[0], roi[1]
                vr0, vc0 = scene.sub_rois[f.vehicle][:2]
                if merged is None:
                    comps[f.vehicle].feed(patch, mask, r0 - vr0, c0 - vc0)
                else:
                    contribution = merged.prepare(patch, mask, r0, c0)
                    if contribution is not None:
                        merged.add(contribution)
                        comps[f.vehicle].add(contribution, vr0, vc0)
                fed += 1
            bar.update(1)
    t_fed = time.perf_counter() - t_images
    if wanted:
        log.warning("mosaic: %d selected frame(s) not found in the logs", len(wanted))
    return fed, t_fed


def _blended(
    comps: dict[str, Compositor], merged: Compositor | None, scene: _Scene
) -> dict[str, tuple[Blended, CanvasGrid, int]]:
    """(image, its grid, images fed) of each mosaic: per vehicle and `MERGED_MOSAIC` (the
    only vehicle's for a single one)."""
    results: dict[str, tuple[Blended, CanvasGrid, int]] = {}
    for v, comp in comps.items():
        results[v] = (comp.result(), scene.grid.sub(scene.sub_rois[v]), comp.fed)
    if merged is not None:
        results[MERGED_MOSAIC] = (merged.result(), scene.grid, merged.fed)
    else:
        results[MERGED_MOSAIC] = results[next(iter(comps))]
    return results


def _placement(cfg: Config, grid: CanvasGrid, ground: GroundModel) -> MapPlacement:
    """Where the mosaics lie on a map: the nav frame's east/north (local CRS) or, with
    geo.origin, UTM fitted over the whole canvas (so every mosaic is placed alike), at the
    height of the ground at its centre."""
    o = cfg.geo.origin
    if o is None:
        return local_placement()
    box = grid.box_ne()
    up_m = -float(ground.z_at(0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])))
    placement = utm_placement(
        o.lat_deg, o.lon_deg, o.alt_m, o.heading_deg, (box[0], box[1], box[2], box[3]), up_m
    )
    if placement.max_fit_error_m > 0.5 * grid.gsd_m:
        log.warning(
            "mosaic: over %.0f x %.0f m the UTM map (an affine) is up to %.2f m off the exact "
            "projection of the nav frame, more than half a pixel (%.3g m)",
            box[2] - box[0],
            box[3] - box[1],
            placement.max_fit_error_m,
            grid.gsd_m,
        )
    return placement


def _write_mosaics(
    out: MosaicFolder,
    results: dict[str, tuple[Blended, CanvasGrid, int]],
    tracks: dict[str, np.ndarray],
    table: LandmarkMap,
    truth: Any,
    gsd: float,
    overlay: bool,
    placement: MapPlacement,
) -> dict[str, MosaicInfo]:
    """Each mosaic's image, world file, CRS and GeoTIFF and (with `overlay`) the tracks,
    landmarks and a scale bar drawn on it; what each covers and, for a simulated run, how it
    aligns with the true ground."""
    observers = [set(o.split(";")) for o in table.observers]
    lm_of = {v: table.p_nav_m[np.array([v in o for o in observers], bool)] for v in tracks}
    infos: dict[str, MosaicInfo] = {}
    for n, (b, g, count) in results.items():
        sub = g.sub((*b.offset_rc, *b.mask.shape))
        transform = placement.raster_transform(sub.n_max, sub.e_min, sub.gsd_m)
        write_png_atomic(out.image(n), b.image, b.mask)
        write_world_file(out.world_file(n), transform)
        write_crs_sidecar(out.image(n), placement.crs_wkt)
        write_geotiff_atomic(out.geotiff(n), b.image, b.mask, transform, placement.crs_wkt)
        if overlay:
            sel = tracks if n == MERGED_MOSAIC else {n: tracks[n]}
            lms = lm_of if n == MERGED_MOSAIC else {n: lm_of[n]}
            write_png_atomic(out.overlay(n), _overlay(b, g, sel, lms), None)
            write_world_file(out.overlay_world_file(n), transform)
            write_crs_sidecar(out.overlay(n), placement.crs_wkt)
        truth_info = None
        if truth is not None:
            ref, ref_ok = resample_reference(truth[0], truth[1], truth[2], sub)
            truth_info = align_to_reference(b.image, b.mask, ref, ref_ok).as_dict(sub.gsd_m)
        infos[n] = MosaicInfo(
            images=count,
            width_px=int(b.mask.shape[1]),
            height_px=int(b.mask.shape[0]),
            covered_m2=round(b.covered_px * gsd * gsd, 1),
            truth=truth_info,
        )
    return infos


def _record_summary(
    summary: MosaicSummary, grid: CanvasGrid, ground: GroundModel, placement: MapPlacement
) -> dict[str, Any]:
    """The mosaic run's summary in run.yaml."""
    return {
        "source": summary.source,
        "gsd_m": summary.gsd_m,
        "canvas_px": [grid.shape[1], grid.shape[0]],
        "map": {
            "crs": placement.crs_name,
            "max_fit_error_m": round(placement.max_fit_error_m, 4),
        },
        "ground": {
            "landmarks": ground.points,
            "inliers": ground.inliers,
            "residual_rms_m": round(ground.residual_rms_m, 3),
            "inlier_threshold_m": round(ground.threshold_m, 3),
            "local_regions": ground.local_regions,
        },
        "mosaics": {n: dataclasses.asdict(i) for n, i in summary.mosaics.items()},
        "union_coverage": round(summary.union_coverage, 4),
        "images_per_s": round(summary.images_per_s, 2),
    }


def run(
    cfg: Config,
    run_dir: Path,
    *,
    source: str | None = None,
    gsd_m: float | None = None,
    log_paths: Sequence[Path] = (),
    force: bool = False,
    progress: bool = False,
) -> MosaicSummary:
    cfg = _with_overrides(cfg, source, gsd_m)
    mc = cfg.mosaic
    layout = RunLayout(run_dir)
    rd = RunDir(run_dir)
    frame_stamps_ns, metas = feature_frame_index(run_dir)
    vehicles = sorted(frame_stamps_ns)
    cfg = dataclasses.replace(cfg, logs=with_run_bindings(cfg.logs, run_dir))
    logs_used = all_log_paths(list(log_paths) or layout.find_logs(metas), cfg.logs)
    require_logs(logs_used)  # a missing log named before the plan reads it
    fuse = layout.fuse(mc.fuse_dir)
    traj_files = _fuse_inputs(fuse, vehicles, mc.source)
    out = layout.mosaic(mosaic_name(mc.source))
    outputs = [
        p
        for n in [*vehicles, MERGED_MOSAIC]
        for p in (out.image(n), out.world_file(n), out.geotiff(n))
    ]
    inputs = [*logs_used, fuse.map_csv, *traj_files.values()]
    # geo.origin is part of the stage's config where it is set (so a run made without it,
    # before the key existed too, is not "another config")
    sections = ("mosaic", "geo.origin") if cfg.geo.origin is not None else ("mosaic",)
    plan = rd.plan(out.name, cfg, sections, inputs, outputs, force)
    if plan.action == "skip":
        log.info("mosaic: %s is up to date (same config and inputs); --force to redo it", out.path)
        return MosaicSummary(run_dir, out.path, True, mc.source)
    check_writable(outputs)  # before the work: a read-only folder, a name too long
    t_start = time.perf_counter()

    table = read_map_csv(fuse.map_csv)
    logs = _open_logs(cfg, logs_used, vehicles)
    tables = _poses(logs, vehicles, mc.source, traj_files)
    cams = {v: logs.rig(v).left for v in vehicles}
    ground = _ground(table, tables, cams, mc, fuse.map_csv)
    frames, limits, gsds = _frames(frame_stamps_ns, tables, cams, ground, mc)
    grid, gsd = _canvas(frames, gsds, mc, run_dir)
    scene = _Scene(ground, cams, limits, grid, _vehicle_rois(frames, grid, mc))
    comps, merged = _compositors(scene.sub_rois, grid, mc)
    fed, t_fed = _feed_images(logs, frames, scene, comps, merged, progress)

    truth = _true_ground(run_dir, logs_used)
    placement = _placement(cfg, grid, ground)
    with atomic_dir(out.path) as tmp:
        tracks = {v: tables[v].p_nav_m for v in sorted(comps)}
        results = _blended(comps, merged, scene)
        infos = _write_mosaics(
            MosaicFolder(tmp), results, tracks, table, truth, gsd, mc.overlay, placement
        )
    union = _union_coverage(results, grid, scene.sub_rois) if merged is not None else 1.0
    wall = time.perf_counter() - t_start
    summary = MosaicSummary(
        run_dir=run_dir,
        out_dir=out.path,
        skipped=False,
        source=mc.source,
        gsd_m=gsd,
        mosaics=infos,
        union_coverage=union,
        ground_local_regions=ground.local_regions,
        images_per_s=fed / t_fed if t_fed > 0 else float("nan"),
        wall_s=wall,
    )
    rd.record(out.name, plan, outputs, _record_summary(summary, grid, ground, placement), wall)
    return summary


def _union_coverage(
    results: dict[str, tuple[Blended, CanvasGrid, int]],
    grid: CanvasGrid,
    sub_rois: dict[str, tuple[int, int, int, int]],
) -> float:
    """Fraction of the union of the vehicles' covered pixels that the merged mosaic covers."""
    union = np.zeros(grid.shape, bool)
    for v, roi in sub_rois.items():
        b = results[v][0]
        r0, c0 = roi[0] + b.offset_rc[0], roi[1] + b.offset_rc[1]
        h, w = b.mask.shape
        union[r0 : r0 + h, c0 : c0 + w] |= b.mask
    merged = np.zeros(grid.shape, bool)
    b = results[MERGED_MOSAIC][0]
    h, w = b.mask.shape
    merged[b.offset_rc[0] : b.offset_rc[0] + h, b.offset_rc[1] : b.offset_rc[1] + w] = b.mask
    n = int(union.sum())
    return float((union & merged).sum() / n) if n else float("nan")
