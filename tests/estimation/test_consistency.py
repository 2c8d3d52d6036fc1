"""The filter's uncertainty tells the truth (issue 15): on a short landmark-mode Monte Carlo
(the benchmark's scenario, `tests/benchmarks/test_fuse_consistency.py`, shortened) the mean
position NEES of the default configuration stays near its expected 3, while the paper's
configuration (`configs/paper.yaml`: new landmarks ranked by the precision of the very
measurement they are initialised from) is several times overconfident: the test fails on
the old filter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from threadpoolctl import threadpool_limits

from cvslam_cli.config import load_config
from cvslam_cli.estimation import stage
from cvslam_cli.estimation.slam import Slam
from cvslam_cli.geometry.rotations import interpolate_positions
from cvslam_cli.io.features_file import load_features
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.sim.scenario import load_scenario
from cvslam_cli.sim.stage import run as simulate
from tests.scenarios import MC_IMU_NOISE_OVERRIDES, monte_carlo_uav_scenario

REPO = Path(__file__).resolve().parents[2]
SEEDS = range(6)
DURATION_S = 10.0


@pytest.fixture(scope="module")
def sims(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("mc")
    path = root / "scenario.yaml"
    path.write_text(yaml.safe_dump(monte_carlo_uav_scenario(0.03, DURATION_S)))
    out = []
    for seed in SEEDS:
        simulate(load_scenario(path, seed=seed), root / f"s{seed}")
        out.append(root / f"s{seed}")
    return out


def _mean_position_nees(sims: list[Path], config_files: tuple[Path, ...]) -> float:
    """Mean over frames (after the first) of the mean over runs of e^T P^-1 e (3-D position
    error against the truth, the filter's 3x3 position covariance), EKF."""
    cfg = load_config(config_files, list(MC_IMU_NOISE_OVERRIDES))
    per_run = []
    for d in sims:
        fs = {"uav1": load_features(d / "features" / "uav1.npz")[0]}
        logs = LogSet([McapLogSource(d / "uav1.mcap")], cfg.logs)
        inputs, truth = stage.build_inputs(cfg, fs, logs)
        with threadpool_limits(limits=1, user_api="blas"):
            res = Slam(inputs, stage.slam_settings(cfg.fuse, "ekf")).run()
        tr, gt = res.tracks["uav1"], truth["uav1"]
        assert res.divergence is None
        e = tr.p_nav_m - interpolate_positions(gt.stamps_ns, gt.p_nav_m, tr.stamps_ns)
        P = tr.pose_cov[:, :3, :3]
        per_run.append(np.einsum("fi,fi->f", e, np.linalg.solve(P, e[..., None])[..., 0]))
    frames = min(len(n) for n in per_run)
    return float(np.mean(np.mean([n[:frames] for n in per_run], axis=0)[1:]))


def test_default_filter_is_consistent_and_the_papers_is_not(sims):
    default = _mean_position_nees(sims, ())
    paper = _mean_position_nees(sims, (REPO / "configs" / "paper.yaml",))
    print(f"\nmean position NEES (3 expected): default {default:.2f}, paper preset {paper:.2f}")
    assert 1.0 < default < 6.0
    assert paper > 2 * default
