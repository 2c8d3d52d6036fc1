"""`make bench`: `cvslam extract` (issue 4) against the plain approach run in the same process.

Plain approach: OpenCV SIFT with default parameters (`cv2.SIFT_create()`: full resolution,
2x upsampled pyramid base, 3 layers, contrast 0.04) on both images, `cv2.BFMatcher` k = 2
nearest over ALL right keypoints and the ratio test at 0.8, then the same triangulation.

1. Per frame, EuRoC V1_01 pairs (752x480, unrectified) and simulated `uav2_paper` pairs
   (752x480, rectified), OpenCV limited to 1 thread (per core, as in the stage's workers;
   our matcher runs in one thread too), best of repeated runs per frame:
   - candidates examined per left keypoint: ours (stereo windows, eq. 20-34) vs brute force
     (= number of right keypoints). Target <= 3% of brute force.
   - matching time on the SAME (adaptive) keypoints: `match_stereo` vs `match_brute_force`
     (the ratio is the matcher's alone); also each approach on its own keypoints.
     Target >= 10x faster.
   - whole frame (detect both + match + triangulate): `process_frame` vs the plain pipeline.
2. Whole stage: `cvslam_cli.features.stage.run` with 2 workers on an MCAP of EuRoC pairs and
   on a 16 s simulated `uav2_paper` log (2 UAVs), vs the plain pipeline run frame after frame
   in this process over the same log (OpenCV's default threads: both cores). Target >= 20
   pairs/s (EuRoC's real-time rate). The stage's wall clock includes starting the 2 spawned
   workers; that start-up, measured alone by mapping a no-op of the stage's module over a
   pool of 2 workers, is also reported apart.
3. Adaptive vs fixed SIFT (`extract.adaptive.enabled=false`, otherwise identical): keypoints
   per image and triangulated matches per frame on stereo pairs rendered straight down over
   the `uav2_paper` world from 100 m above ground (the scenario's altitude) where the camera
   footprint is the most uniformly smooth (desert) or busy (urban), and from 300 m (0.67 m
   per pixel) over the same world made all urban (`terrain.urban_fraction=1.0`; no 500 m x
   320 m footprint of the scenario's own world is all urban); on the simulated log, EuRoC and
   KITTI. Band: `extract.adaptive.features_min..features_max` keypoints per image. Adaptive
   must stay inside it everywhere; fixed SIFT falls below it on smooth ground and far above
   it on busy ground seen from 300 m (at 100 m it stays inside).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from cvslam_cli.config import ExtractConfig, load_config
from cvslam_cli.features.matching import match_stereo
from cvslam_cli.features.sift import detect_and_describe, to_grey_u8
from cvslam_cli.features.stage import _csv_text, process_frame, run, stereo_limits
from cvslam_cli.features.windows import undistort_keypoints
from cvslam_cli.geometry.camera import StereoRig
from cvslam_cli.geometry.projection import pixel_rays
from cvslam_cli.geometry.rotations import make_T
from cvslam_cli.geometry.stereo import projection_matrices, triangulate, triangulation_covariance
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.parallel import ordered_map
from cvslam_cli.records.log import StereoFrame
from cvslam_cli.sim.render import photometric
from cvslam_cli.sim.scenario import SCENARIO_DIR, Scenario, load_scenario
from cvslam_cli.sim.stage import build_world
from cvslam_cli.sim.stage import run as simulate
from cvslam_cli.sim.terrain import Terrain, render_terrain_view
from cvslam_cli.sim.vehicles import R_BODY_CAM_DOWN, build_rig
from tests.conftest import shared_data_dir
from tests.features.reference_matcher import match_brute_force

SCENARIO = SCENARIO_DIR / "uav2_paper.yaml"
SIM_SETS = ["duration_s=16.0"]  # uav1: 160 pairs, uav2 (starts at 8 s): 80 pairs
PLAIN_RATIO = 0.8
FRAMES_PER_DATASET = 12  # per-frame timings: frames spread over each log
MATCH_REPEATS = 10  # matching timings: best of this many consecutive runs per frame


# ----------------------------------------------------------------------------- data


def _data(name: str) -> Path:
    path = shared_data_dir() / name
    if not path.is_dir():
        pytest.skip(f"real data {path} not found (set CVSLAM_SHARED_DATA)")
    return path


@dataclass
class Log:
    name: str
    paths: list[Path]
    frames: list[tuple[np.ndarray, np.ndarray, StereoRig]]  # every stereo pair, time order


def _read(name: str, paths: list[Path]) -> Log:
    cfg = load_config()
    logs = LogSet([McapLogSource(p) for p in paths], cfg.logs)
    vehicles = [v for v, vt in logs.vehicles.items() if vt.has_stereo]
    rigs = {v: logs.rig(v) for v in vehicles}
    frames = [
        (to_grey_u8(r.left.image), to_grey_u8(r.right.image), rigs[r.vehicle])
        for r in logs.records(vehicles=vehicles, roles=("left_image", "right_image"))
        if isinstance(r, StereoFrame)
    ]
    return Log(name, paths, frames)


@pytest.fixture(scope="module")
def tmp(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("extract_bench")


@pytest.fixture(scope="module")
def sim_log(tmp: Path) -> Log:
    t = time.perf_counter()
    out = simulate(load_scenario(SCENARIO, SIM_SETS), tmp / "sim", workers=2).out_dir
    log = _read("simulated uav2_paper", [out / "uav1.mcap", out / "uav2.mcap"])
    print(
        f"\n[bench] simulated uav2_paper ({', '.join(SIM_SETS)}): {len(log.frames)} pairs "
        f"in {time.perf_counter() - t:.1f} s"
    )
    return log


@pytest.fixture(scope="module")
def euroc_log(tmp: Path) -> Log:
    from cvslam_cli.io.importers.euroc import import_euroc

    path = tmp / "euroc.mcap"
    import_euroc(_data("euroc_v101_micro") / "mav0", path, "uav1")
    return _read("EuRoC V1_01", [path])


@pytest.fixture(scope="module")
def kitti_log(tmp: Path) -> Log:
    from cvslam_cli.io.importers.kitti import import_kitti

    path = tmp / "kitti.mcap"
    import_kitti(_data("kitti_clip_a"), path, "uav1")
    return _read("KITTI clip a", [path])


# ----------------------------------------------------------------------------- helpers


def _best(fn: Callable[[], Any], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _spread(frames: list, n: int) -> list:
    return [frames[i] for i in np.linspace(0, len(frames) - 1, min(n, len(frames))).astype(int)]


def _triangulate(
    uvl: np.ndarray, uvr: np.ndarray, left: np.ndarray, right: np.ndarray, rig: StereoRig,
    cfg: ExtractConfig,
) -> int:  # fmt: skip
    """The triangulation step of `process_frame` (points in front, in range, covariance)."""
    _, max_range = stereo_limits(rig, cfg)
    M_l, M_r = projection_matrices(rig)
    ul, ur = uvl[left].astype(float), uvr[right].astype(float)
    p = triangulate(M_l, M_r, ul, ur) if left.size else np.zeros((0, 3))
    T_rl = np.linalg.inv(rig.T_left_right)
    z_right = p @ T_rl[2, :3] + T_rl[2, 3]
    keep = (p[:, 2] > 0) & (z_right > 0) & (np.linalg.norm(p, axis=1) <= max_range)
    triangulation_covariance(M_l, M_r, ul[keep], ur[keep], cfg.stereo.pixel_sigma_px, p[keep])
    return int(keep.sum())


def _plain_detect(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    kps, desc = cv2.SIFT_create().detectAndCompute(img, None)
    uv = cv2.KeyPoint_convert(kps).reshape(-1, 2) if kps else np.zeros((0, 2), np.float32)
    return uv, desc if desc is not None else np.zeros((0, 128), np.float32)


def _plain_frame(left: np.ndarray, right: np.ndarray, rig: StereoRig, cfg: ExtractConfig) -> int:
    """The plain pipeline: default OpenCV SIFT on both, brute-force knn + ratio 0.8, then
    the same undistortion and triangulation as ours."""
    uvl, dl = _plain_detect(left)
    uvr, dr = _plain_detect(right)
    m = match_brute_force(dl, dr, PLAIN_RATIO)
    ul, ur = undistort_keypoints(rig.left, uvl), undistort_keypoints(rig.right, uvr)
    return _triangulate(ul, ur, m.left, m.right, rig, cfg)


# ----------------------------------------------------------------------------- 1. per frame


@dataclass
class PerFrame:
    cand_ours: float  # mean candidates examined per left keypoint
    cand_bf: float  # mean number of right keypoints
    match_ours_s: float  # mean per frame, adaptive keypoints
    match_bf_s: float  # same keypoints, brute force
    match_bf_own_s: float  # brute force on default SIFT's keypoints
    kp_ours: float
    kp_plain: float
    frame_ours_s: float
    frame_plain_s: float
    n: int


def _measure(left: np.ndarray, right: np.ndarray, rig: StereoRig, cfg: ExtractConfig) -> tuple:
    kl, _ = detect_and_describe(left, cfg.sift, cfg.adaptive)
    kr, _ = detect_and_describe(right, cfg.sift, cfg.adaptive)
    uvl = undistort_keypoints(rig.left, kl.uv_raw_px)
    uvr = undistort_keypoints(rig.right, kr.uv_raw_px)
    m = match_stereo(uvl, kl.desc, uvr, kr.desc, rig, cfg.stereo)
    t_ours = _best(lambda: match_stereo(uvl, kl.desc, uvr, kr.desc, rig, cfg.stereo), MATCH_REPEATS)
    t_bf = _best(lambda: match_brute_force(kl.desc, kr.desc, PLAIN_RATIO), MATCH_REPEATS)
    (_, pdl), (_, pdr) = _plain_detect(left), _plain_detect(right)
    t_bf_own = _best(lambda: match_brute_force(pdl, pdr, PLAIN_RATIO), MATCH_REPEATS)
    f_ours = _best(lambda: process_frame(left, right, rig, cfg), 2)
    f_plain = _best(lambda: _plain_frame(left, right, rig, cfg), 2)
    return (
        m.candidates_per_keypoint, m.n_right, t_ours, t_bf, t_bf_own,
        (len(kl) + len(kr)) / 2, (len(pdl) + len(pdr)) / 2, f_ours, f_plain,
    )  # fmt: skip


@pytest.fixture(scope="module", params=["euroc", "sim"])
def per_frame(request: pytest.FixtureRequest) -> tuple[str, PerFrame]:
    log: Log = request.getfixturevalue(f"{request.param}_log")
    cfg = load_config().extract
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # per core, as in the stage's workers (our matcher is 1 thread)
    try:
        rows = [_measure(*frame, cfg) for frame in _spread(log.frames, FRAMES_PER_DATASET)]
    finally:
        cv2.setNumThreads(threads)
    mean = np.mean(np.array(rows, float), axis=0)
    return log.name, PerFrame(*(float(x) for x in mean), n=len(rows))


def test_candidates_per_keypoint(per_frame: tuple[str, PerFrame]) -> None:
    name, r = per_frame
    share = r.cand_ours / r.cand_bf
    print(
        f"\n[bench] {name} ({r.n} frames), candidates examined per left keypoint: stereo "
        f"windows {r.cand_ours:.2f} | brute force (all right keypoints) {r.cand_bf:.0f} | "
        f"ratio {100 * share:.2f}% | target <= 3%: {'met' if share <= 0.03 else 'NOT met'}"
    )
    assert share <= 0.03


def test_matching_time(per_frame: tuple[str, PerFrame]) -> None:
    name, r = per_frame
    speedup = r.match_bf_s / r.match_ours_s
    own = r.match_bf_own_s / r.match_ours_s
    verdict = "met" if speedup >= 10 else "NOT met"
    print(
        f"\n[bench] {name} ({r.n} frames), matching time per frame, same adaptive keypoints "
        f"({r.kp_ours:.0f} per image): stereo windows {1e3 * r.match_ours_s:.2f} ms | "
        f"cv2.BFMatcher knn + ratio {1e3 * r.match_bf_s:.2f} ms | {speedup:.1f}x faster | "
        f"target >= 10x: {verdict}"
        f"\n[bench] {name}, matching time, each on its own keypoints: ours "
        f"{1e3 * r.match_ours_s:.2f} ms | brute force on default SIFT's {r.kp_plain:.0f} "
        f"keypoints per image {1e3 * r.match_bf_own_s:.2f} ms | {own:.1f}x faster"
    )
    assert speedup > 3  # a floor that holds under load (quiet figures: BENCHMARKS.md)
    if speedup < 10:
        pytest.xfail(f"{name}: matching {speedup:.1f}x faster than brute force, target >= 10x")


def test_frame_time(per_frame: tuple[str, PerFrame]) -> None:
    name, r = per_frame
    print(
        f"\n[bench] {name} ({r.n} frames), whole frame (detect both + match + triangulate): "
        f"cvslam {1e3 * r.frame_ours_s:.1f} ms | plain (cv2.SIFT_create() + BFMatcher knn + "
        f"ratio {PLAIN_RATIO}) {1e3 * r.frame_plain_s:.1f} ms | "
        f"{r.frame_plain_s / r.frame_ours_s:.1f}x faster"
    )
    assert r.frame_ours_s < r.frame_plain_s


# ----------------------------------------------------------------------------- 2. stage


def _startup_s(log: Log) -> float:
    """Starting the stage's 2 spawned workers (imports of the stage module, state pickled
    once per worker), with a no-op of the stage's own module as the job."""
    cfg = load_config()
    state = {"rigs": {"uav1": log.frames[0][2]}, "cfg": cfg.extract}
    t = time.perf_counter()
    list(ordered_map(_csv_text, [[], []], workers=2, state=state))
    return time.perf_counter() - t


@pytest.mark.parametrize("name", ["euroc", "sim"])
def test_stage_throughput(name: str, request: pytest.FixtureRequest, tmp: Path) -> None:
    log: Log = request.getfixturevalue(f"{name}_log")
    cfg = load_config()
    n_plain = min(24, len(log.frames))
    t = time.perf_counter()
    for left, right, rig in log.frames[:n_plain]:
        _plain_frame(left, right, rig, cfg.extract)
    plain = n_plain / (time.perf_counter() - t)

    startup = _startup_s(log)
    t = time.perf_counter()
    summary = run(cfg, log.paths, tmp / f"run_{name}", workers=2, force=True)
    wall = time.perf_counter() - t
    pairs = sum(v.frames for v in summary.vehicles.values())
    assert pairs == len(log.frames)
    ours, steady = pairs / wall, pairs / (wall - startup)
    print(
        f"\n[bench] stage {log.name}, {pairs} pairs, 2 workers: {ours:.1f} pairs/s "
        f"({wall:.2f} s wall; {steady:.1f} pairs/s without the {startup:.2f} s worker "
        f"start-up) | plain pipeline, 1 process: {plain:.1f} pairs/s | ratio {ours / plain:.1f}"
        f" | target >= 20: {'met' if ours >= 20 else 'NOT met'}"
        + ("" if ours >= 20 else f" (without start-up: {'met' if steady >= 20 else 'NOT met'})")
    )
    assert steady >= 20
    if ours < 20:
        pytest.xfail(f"{log.name}: {ours:.1f} pairs/s including worker start-up, target >= 20")


# ----------------------------------------------------------------------------- 3. adaptive


def _views(sc: Scenario, world: Terrain, busy: bool, agl_m: float, n: int) -> Iterator[tuple]:
    """n stereo pairs rendered straight down from `agl_m` above ground over the places whose
    camera footprint is the most uniformly smooth (busy=False) or busy (busy=True)."""
    rig = build_rig("uav1", sc.vehicles["uav1"].camera)
    rig_cams = (rig.left, rig.right)
    rays = (pixel_rays(rig.left), pixel_rays(rig.right))
    px = world.spec.texture_px_per_m
    weight = cv2.resize(
        world.urban_weight, None, fx=1 / px, fy=1 / px, interpolation=cv2.INTER_AREA
    )
    # footprint (east x north, metres) of the down-looking camera at yaw 0: image x = east
    cam = rig.left
    fw, fh = int(cam.width / cam.fx * agl_m) | 1, int(cam.height / cam.fy * agl_m) | 1
    share = cv2.blur(weight, (fw, fh), borderType=cv2.BORDER_REPLICATE)
    my, mx = fh // 2 + 2, fw // 2 + 2
    inner = share[my:-my, mx:-mx]
    score = inner if busy else -inner
    order = np.argsort(score, axis=None)[::-1]
    picked: list[tuple[int, int]] = []
    for k in order:  # best places, at least 25 m apart
        r, c = divmod(int(k), inner.shape[1])
        if all(abs(r - a) + abs(c - b) >= 25 for a, b in picked):
            picked.append((r, c))
        if len(picked) == n:
            break
    rng = np.random.default_rng(7)
    ph = sc.photometry
    n0, e0 = world.spec.origin_nav_m
    for r, c in picked:
        north, east = n0 + my + r + 0.5, e0 + mx + c + 0.5
        down = -(float(world.elevation_at(north, east)) + agl_m)
        T = make_T(R_BODY_CAM_DOWN, np.array([north, east, down]))
        images = []
        for camera, T_cam, ray in zip(rig_cams, (T, T @ rig.T_left_right), rays, strict=True):
            res = render_terrain_view(world, camera, T_cam, rays=ray)
            gain = 1.0 + ph.gain_sigma * rng.standard_normal()
            offset = ph.offset_sigma * rng.standard_normal()
            noise = ph.noise_sigma_dn
            images.append(
                photometric(res.radiance, gain=gain, offset=offset, noise_sigma=noise, rng=rng)
            )
        yield images[0], images[1], rig, float(inner[r, c])


@dataclass
class Counts:
    kp: np.ndarray  # keypoints per image (both images of every frame)
    matches: np.ndarray  # triangulated matches per frame


def _counts(frames: list[tuple], cfg: ExtractConfig) -> Counts:
    kp, matches = [], []
    for left, right, rig, *_ in frames:
        *_, stats = process_frame(left, right, rig, cfg)
        kp += [stats["kp_left"], stats["kp_right"]]
        matches.append(stats["points"])
    return Counts(np.array(kp), np.array(matches))


def _mmm(a: np.ndarray) -> str:
    return f"{a.min():.0f} / {np.median(a):.0f} / {a.max():.0f}"


def test_adaptive_vs_fixed(sim_log: Log, request: pytest.FixtureRequest) -> None:
    adaptive = load_config().extract
    fixed = load_config(overrides=["extract.adaptive.enabled=false"]).extract
    lo, hi = adaptive.adaptive.features_min, adaptive.adaptive.features_max

    sc = load_scenario(SCENARIO, SIM_SETS)
    world = build_world(sc)
    urban_sets = [*SIM_SETS, "terrain.urban_fraction=1.0"]
    sc_urban = load_scenario(SCENARIO, urban_sets)
    urban = build_world(sc_urban)
    sets: dict[str, list[tuple]] = {
        "uav2_paper smooth regions, 100 m": list(_views(sc, world, False, 100.0, 6)),
        "uav2_paper busy regions, 100 m": list(_views(sc, world, True, 100.0, 6)),
        "uav2_paper all urban, 300 m": list(_views(sc_urban, urban, True, 300.0, 6)),
        "uav2_paper simulated log": sim_log.frames[::8],
    }
    for name in ("euroc", "kitti"):
        try:
            log: Log = request.getfixturevalue(f"{name}_log")
        except pytest.skip.Exception as exc:
            print(f"\n[bench] adaptive vs fixed: {name} skipped ({exc})")
            continue
        sets[log.name] = log.frames[::4] if name == "euroc" else log.frames[::3]

    print(
        f"\n[bench] adaptive vs fixed SIFT, band [{lo}, {hi}] keypoints per image; keypoints "
        "per image and triangulated matches per frame as min / median / max\n"
        "[bench] | images | frames | adaptive keypoints | fixed keypoints | adaptive matches |"
        " fixed matches | fixed images below / above band |"
    )
    results: dict[str, tuple[Counts, Counts]] = {}
    for name, frames in sets.items():
        a, f = _counts(frames, adaptive), _counts(frames, fixed)
        results[name] = (a, f)
        below, above = 100 * np.mean(f.kp < lo), 100 * np.mean(f.kp > hi)
        print(
            f"[bench] | {name} | {len(frames)} | {_mmm(a.kp)} | {_mmm(f.kp)} | "
            f"{_mmm(a.matches)} | {_mmm(f.matches)} | {below:.0f}% / {above:.0f}% |"
        )
    for name, (a, _) in results.items():
        assert lo <= a.kp.min() and a.kp.max() <= hi, name
    smooth = results["uav2_paper smooth regions, 100 m"][1]
    busy = results["uav2_paper all urban, 300 m"][1]
    assert np.mean(smooth.kp < lo) >= 0.9  # fixed SIFT starves on smooth ground
    assert np.median(busy.kp) > 1.2 * hi  # and floods on busy ground seen from high up
