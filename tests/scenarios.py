"""Scenario builders shared by the tests of several stages (simulate, extract, fuse, the CLI)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cvslam_cli.sim.imu import ImuNoise

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


VEHICLE = "uav1"
# the Monte Carlo's IMU: 10x the simulator's default white noise, and the filter told so
MC_IMU_NOISE = {"accel_noise_density": 0.02, "gyro_noise_density": 1.7e-3}
# A NEES means something only when the filter is told the statistics the truth was drawn
# from: its IMU noise, the spread of the simulator's turn-on biases (`sim.imu.ImuNoise`
# defaults), and, since it starts from the true first pose, a small initial uncertainty
# (the defaults' 0.1 m and 5 mrad, never realised, would stay in the unobservable position
# and heading and read as a conservative filter).
MC_FILTER_OVERRIDES = (
    f"fuse.motion.accel_noise_density={MC_IMU_NOISE['accel_noise_density']}",
    f"fuse.motion.gyro_noise_density={MC_IMU_NOISE['gyro_noise_density']}",
    f"fuse.initial.accel_bias_sigma_m_s2={ImuNoise().accel_bias_initial_sigma}",
    f"fuse.initial.gyro_bias_sigma_rad_s={ImuNoise().gyro_bias_initial_sigma}",
    "fuse.initial.position_sigma_m=0.01",
    "fuse.initial.attitude_sigma_rad=0.0005",
)


def monte_carlo_uav_scenario(
    outlier_fraction: float, duration_s: float, lookalike_fraction: float = 0.0
) -> dict[str, Any]:
    """The fuse Monte Carlo scenario (the seed is set per run): one UAV at 10 m/s, 100 m above
    terrain with 20 m of relief, a downward stereo camera like `uav2_paper`'s, landmark mode
    with `outlier_fraction` random wrong matches and `lookalike_fraction` look-alikes of
    landmarks in view (`sim.scenario.LandmarkMode`), a consumer IMU (`MC_IMU_NOISE`)."""
    return {
        "name": "fuse_mc",
        "mode": "landmarks",
        "duration_s": duration_s,
        "seed": 0,
        "world": "terrain",
        "terrain": {
            "size_m": [400.0, 400.0],
            "origin_nav_m": [-200.0, -200.0],
            "texture_px_per_m": 1.0,
            "relief_m": 20.0,
            "relief_scale_m": 100.0,
            "region_scale_m": 100.0,
        },
        "landmarks": {
            "outlier_fraction": outlier_fraction,
            **({"lookalike_fraction": lookalike_fraction} if lookalike_fraction else {}),
        },
        "vehicles": {
            VEHICLE: {
                "closed": True,
                "speed_m_s": 10.0,
                "waypoints_nav_m": [
                    [0.0, -50.0, -100.0],
                    [50.0, 0.0, -100.0],
                    [0.0, 50.0, -100.0],
                    [-50.0, 0.0, -100.0],
                ],
                "camera": {
                    "mount": "down",
                    "width": 752,
                    "height": 480,
                    "fx": 450.0,
                    "fy": 450.0,
                    "cx": 375.5,
                    "cy": 239.5,
                    "baseline_m": 1.5,
                    "rate_hz": 10.0,
                },
                "imu": dict(MC_IMU_NOISE),
            }
        },
    }


def simulate_seeds(scenario: dict[str, Any], root: Path, seeds: Any) -> list[Path]:
    """The scenario mapping `scenario` (written to `root`/scenario.yaml) simulated with each
    of `seeds` into `root`/s<seed>; those folders."""
    from cvslam_cli.sim.scenario import load_scenario
    from cvslam_cli.sim.stage import run as simulate

    path = root / "scenario.yaml"
    path.write_text(yaml.safe_dump(scenario))
    out = []
    for seed in seeds:
        simulate(load_scenario(path, seed=seed), root / f"s{seed}")
        out.append(root / f"s{seed}")
    return out


def loop_uav_scenario(
    outlier_fraction: float, duration_s: float, lookalike_fraction: float = 0.0
) -> dict[str, Any]:
    """The Monte Carlo UAV (`monte_carlo_uav_scenario`) on a 60 m diamond, 60 m up, at
    20 m/s: one lap in 17 s, the ground of its start out of view half of it, each landmark
    in view for ~3 s (against ~10 s for the Monte Carlo's), the heading turned 90 degrees at
    each corner."""
    sc = monte_carlo_uav_scenario(outlier_fraction, duration_s, lookalike_fraction)
    v = sc["vehicles"][VEHICLE]
    v["speed_m_s"] = 20.0
    v["waypoints_nav_m"] = [[0.0, -60.0, -60.0], [60.0, 0.0, -60.0], [0.0, 60.0, -60.0],
                            [-60.0, 0.0, -60.0]]  # fmt: skip
    return sc


def simulate_loop_uav(root: Path, duration_s: float, seeds: Any) -> list[Path]:
    """`loop_uav_scenario` with 3 % wrong matches simulated for `duration_s` with each of
    `seeds` into `root`/s<seed>."""
    return simulate_seeds(loop_uav_scenario(0.03, duration_s), root, seeds)


# The state rows a vehicle's prior sets from the ground truth (fuse.initial.source), which a
# Monte Carlo run starts away from the truth by a draw of P0 (`from_prior`); the biases' truth
# is already such a draw (the simulator's turn-on biases, the filter's prior around zero).
FROM_TRUTH = ("p_n", "p_e", "p_d", "v_x", "v_y", "v_z", "roll", "pitch", "yaw")


def from_prior(inputs: list[Any], seed: int) -> list[Any]:
    """The vehicles of `inputs` with their initial states drawn from their priors around the
    truth: x0 + L n on the `FROM_TRUTH` rows (L L^T their block of P0, n ~ N(0, I) from
    `seed`, a stream apart from the simulator's). The NEES of a Monte Carlo follows its
    chi-square only when the initial error follows P0 (Bar-Shalom, Li and Kirubarajan 2001,
    5.4); a filter started at the truth itself reads below its band until it has forgotten
    its prior."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,)))
    out = []
    for v in inputs:
        rows = [i for i, name in enumerate(v.model.state_names) if name in FROM_TRUTH]
        L = np.linalg.cholesky(v.P0[np.ix_(rows, rows)])
        x0 = v.x0.copy()
        x0[rows] += L @ rng.standard_normal(len(rows))
        out.append(dataclasses.replace(v, x0=x0))
    return out


def ekf_on_simulation(
    sim_dir: Path,
    cfg: Any,
    edit: Callable[[Any], Any] | None = None,
    initial_error_seed: int | None = None,
    edit_inputs: Callable[[list[Any]], list[Any]] | None = None,
) -> tuple[Any, Any]:
    """The EKF over a simulated one-UAV run (`uav1`, landmark mode) with config `cfg`: its
    SlamResult and uav1's ground-truth PoseTable (one BLAS thread: the Monte Carlo tests'
    figures stay bit for bit); `edit` changes the feature set first (e.g. `blackout`);
    `initial_error_seed`: start from a draw of the prior (`from_prior`), not the truth;
    `edit_inputs` changes the vehicle inputs (e.g. their motion samples) last."""
    from threadpoolctl import threadpool_limits

    from cvslam_cli.estimation import stage
    from cvslam_cli.estimation.slam import Slam
    from cvslam_cli.io.features_file import load_features
    from cvslam_cli.io.logs import LogSet
    from cvslam_cli.io.mcap_source import McapLogSource

    fs = {"uav1": load_features(sim_dir / "features" / "uav1.npz")[0]}
    if edit is not None:
        fs = {k: edit(v) for k, v in fs.items()}
    logs = LogSet([McapLogSource(sim_dir / "uav1.mcap")], cfg.logs)
    inputs, truth = stage.build_inputs(cfg, fs, logs)
    if initial_error_seed is not None:
        inputs = from_prior(inputs, initial_error_seed)
    if edit_inputs is not None:
        inputs = edit_inputs(inputs)
    with threadpool_limits(limits=1, user_api="blas"):
        res = Slam(inputs, stage.settings_for(cfg.fuse, "ekf", inputs)).run()
    return res, truth["uav1"]


def blackout(fs: Any, start_s: float, end_s: float) -> Any:
    """The feature set `fs` with no stereo match in the frames from `start_s` to `end_s`
    after its first (a camera that saw nothing: fog, a lens cap, a featureless stretch);
    the keypoints are kept."""
    t_s = (fs.frame_stamp_ns - fs.frame_stamp_ns[0]) * 1e-9
    dark = (t_s >= start_s) & (t_s < end_s)
    counts = np.diff(fs.match_offsets)
    keep = np.repeat(~dark, counts)
    counts[dark] = 0
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    matches = {
        f.name: getattr(fs, f.name)[keep]
        for f in dataclasses.fields(fs)
        if f.name.startswith("match_") and f.name != "match_offsets"
    }
    return dataclasses.replace(fs, match_offsets=offsets, **matches)


def accelerometer_glitch(
    start_s: float, duration_s: float, m_s2: float
) -> Callable[[list[Any]], list[Any]]:
    """An `edit_inputs` for `ekf_on_simulation`: every vehicle's accelerometer `m_s2` off along
    its body x from `start_s` to `start_s + duration_s` after its start (a bump, or an IMU
    saturating), which the filter cannot know of."""

    def edit(inputs: list[Any]) -> list[Any]:
        out = []
        for v in inputs:
            t_s = (v.motion_stamps_ns - v.start_ns) * 1e-9
            U = v.motion_inputs.copy()
            U[(t_s >= start_s) & (t_s < start_s + duration_s), 0] += m_s2
            out.append(dataclasses.replace(v, motion_inputs=U))
        return out

    return edit
