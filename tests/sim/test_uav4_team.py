"""`configs/scenarios/uav4_team.yaml`: the four-UAV team of the cooperative benchmark
(tests/benchmarks/test_fuse_coop.py) loads, flies the geometry its header describes, and
simulates (landmark mode, mission stretched to a few seconds)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cvslam_cli.io.features_file import load_features
from cvslam_cli.sim.scenario import SCENARIO_DIR, load_scenario, resolve_scenario_path
from cvslam_cli.sim.stage import SIM_EPOCH_NS
from cvslam_cli.sim.vehicles import build_path

TEAM = SCENARIO_DIR / "uav4_team.yaml"
VEHICLES = ["uav1", "uav2", "uav3", "uav4"]


def _positions(sc, step_s: float = 0.5) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per vehicle (times (K,), horizontal positions (K, 2)) from its start to the end."""
    out = {}
    for name, v in sc.vehicles.items():
        path = build_path(name, v, sc.duration_s, str(TEAM))  # an open path must fit
        t = np.arange(v.start_s, sc.duration_s + 1e-9, step_s)
        out[name] = (t, path.sample(t).p_nav_m[:, :2])
    return out


def _first_overlap_s(pos, vehicle: str, radius_m: float, lag_s: float) -> float:
    """The first time `vehicle` is within `radius_m` (horizontally) of where another
    vehicle was at least `lag_s` earlier (inf if never)."""
    t, p = pos[vehicle]
    first = np.inf
    for other, (to, po) in pos.items():
        if other == vehicle:
            continue
        d = np.linalg.norm(p[:, None] - po[None], axis=2)
        hit = (d < radius_m) & (to[None] <= t[:, None] - lag_s)
        rows = np.flatnonzero(hit.any(axis=1))
        if len(rows):
            first = min(first, float(t[rows[0]]))
    return first


def test_team_geometry() -> None:
    sc = load_scenario(resolve_scenario_path(Path("uav4_team")))
    paper = load_scenario(SCENARIO_DIR / "uav2_paper.yaml")
    assert sorted(sc.vehicles) == VEHICLES and sc.duration_s == paper.duration_s
    # uav1 and uav2 as in uav2_paper, over the same terrain
    assert sc.terrain == paper.terrain and sc.landmarks == paper.landmarks
    for name in ("uav1", "uav2"):
        assert sc.vehicles[name] == paper.vehicles[name]
    assert {v.camera for v in sc.vehicles.values()} == {paper.vehicles["uav1"].camera}
    starts = [sc.vehicles[v].start_s for v in VEHICLES]
    assert starts == sorted(starts) and len(set(starts)) == 4  # staggered
    pos = _positions(sc)
    # the ground in view (< 100 m from below the vehicle) stays on the terrain
    centre = np.add(sc.terrain.origin_nav_m, np.divide(sc.terrain.size_m, 2.0))
    half = np.divide(sc.terrain.size_m, 2.0) - 100.0
    for _, p in pos.values():
        assert np.all(np.abs(p - centre) < half)
    # uav3 and uav4 first fly alone over new ground, then over ground mapped by the others
    # at least 10 s before (image footprint ~167 x 107 m at 100 m: 60 m apart overlap a lot)
    for name in ("uav3", "uav4"):
        start = sc.vehicles[name].start_s
        first = _first_overlap_s(pos, name, radius_m=60.0, lag_s=10.0)
        assert start + 15.0 < first < sc.duration_s - 5.0, (name, start, first)


def test_simulate_landmarks_short(cvslam, tmp_path: Path) -> None:
    """`cvslam simulate uav4_team --set mode=landmarks --duration 6`: the same mission 10x
    faster; each vehicle starts at its (scaled) time, and uav3 and uav4 observe landmarks
    that another vehicle observed before them (type-2 re-observations for the filter)."""
    out = tmp_path / "team"
    res = cvslam("simulate", "uav4_team", "-o", out, "--set", "mode=landmarks", "--duration", "6")
    assert res.code == 0, res.err
    sc = load_scenario(out / "scenario.yaml")
    assert sc.mode == "landmarks" and sc.duration_s == 6.0
    first_seen: dict[str, dict[int, int]] = {}
    for name in VEHICLES:
        assert (out / f"{name}.mcap").is_file()
        fs, _ = load_features(out / "features" / f"{name}.npz")
        start_ns = SIM_EPOCH_NS + round(sc.vehicles[name].start_s * 1e9)
        assert fs.frame_stamp_ns[0] == start_ns
        assert fs.n_frames == round((6.0 - sc.vehicles[name].start_s) * 10) + 1  # 10 Hz
        frame = np.repeat(np.arange(fs.n_frames), np.diff(fs.match_offsets))
        ids = fs.match_landmark_id
        real = ids >= 0
        stamp = fs.frame_stamp_ns[frame[real]]
        seen: dict[int, int] = {}
        for i, s in zip(ids[real][::-1], stamp[::-1], strict=True):
            seen[int(i)] = int(s)  # the earliest stamp wins (reversed order)
        first_seen[name] = seen
    for name in ("uav3", "uav4"):
        others = {}
        for o in VEHICLES:
            if o != name:
                for i, s in first_seen[o].items():
                    others[i] = min(s, others.get(i, s))
        again = [i for i, s in first_seen[name].items() if i in others and others[i] < s]
        assert len(again) > 50, (name, len(again))
