"""Scenario builders shared by the tests of several stages (simulate, extract, fuse, the CLI)."""

from __future__ import annotations

from pathlib import Path

import yaml

SMALL_CAMERA = {
    "mount": "down",
    "width": 188,
    "height": 120,
    "fx": 112.5,
    "fy": 112.5,
    "cx": 93.5,
    "cy": 59.5,
    "baseline_m": 1.5,
    "rate_hz": 5.0,
}


def small_uav_scenario(tmp_path: Path, **changes: object) -> Path:
    """Write `small.yaml` in `tmp_path`: 6 s over a 300 m terrain, uav1 on a closed square
    loop and uav2 (from 1 s) on an open path, both with `SMALL_CAMERA`. `changes`: dotted
    keys to set, e.g. `duration_s=2.0`, `**{"vehicles.uav1.camera.width": 376}`."""
    sc = {
        "name": "small",
        "duration_s": 6.0,
        "seed": 3,
        "world": "terrain",
        "terrain": {
            "size_m": [300.0, 300.0],
            "origin_nav_m": [-150.0, -150.0],
            "texture_px_per_m": 2.0,
            "relief_m": 20.0,
            "relief_scale_m": 80.0,
            "region_scale_m": 100.0,
        },
        "vehicles": {
            "uav1": {
                "closed": True,
                "speed_m_s": 10.0,
                "camera": dict(SMALL_CAMERA),
                "waypoints_nav_m": [[0, -30, -80], [30, 0, -80], [0, 30, -80], [-30, 0, -80]],
            },
            "uav2": {
                "start_s": 1.0,
                "speed_m_s": 10.0,
                "camera": dict(SMALL_CAMERA),
                "waypoints_nav_m": [[-60, -60, -85], [0, -10, -85], [60, 60, -85]],
            },
        },
    }
    for key, value in changes.items():
        node = sc
        *parents, last = key.split(".")
        for p in parents:
            node = node[p]
        node[last] = value
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(sc))
    return path
