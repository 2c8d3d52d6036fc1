"""`cvslam fuse` on the real KITTI clips (constant-velocity model, no IMU): the estimate
follows the ground truth. Figures printed with -s: ATE after SE3 / Sim3 alignment, drift
per 100 m."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.config import load_config
from cvslam_cli.evaluation.align import umeyama
from cvslam_cli.geometry.rotations import interpolate_positions
from cvslam_cli.io.logs import LogSet
from cvslam_cli.io.mcap_source import McapLogSource
from cvslam_cli.io.trajectory import read_tum
from cvslam_cli.records.log import PoseRecord
from cvslam_cli.records.poses import PoseTable

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module", params=["a", "b"])
def kitti_run(request, shared_data, tmp_path_factory, cvslam_module):
    clip = shared_data / f"kitti_clip_{request.param}"
    if not clip.is_dir():
        pytest.skip(f"{clip} not found")
    run = tmp_path_factory.mktemp(f"kitti_{request.param}")
    log = run / "car.mcap"
    assert cvslam_module("-q", "import", "kitti", clip, "--vehicle", "car", "-o", log) == 0
    assert cvslam_module("-q", "extract", log, "-o", run) == 0
    assert cvslam_module("-q", "fuse", run, "--config", REPO / "configs" / "kitti.yaml") == 0
    return request.param, run


@pytest.fixture(scope="module")
def cvslam_module():
    from cvslam_cli.cli import main

    def run(*args: object) -> int:
        try:
            main([str(a) for a in args])
        except SystemExit as exc:
            return int(exc.code or 0)
        return 0

    return run


def test_kitti_runs_with_no_motion_model_setting(kitti_run):
    """No IMU, no odometry, nothing about the motion model in the config: constant velocity."""
    import yaml

    from cvslam_cli.io.rundir import RunDir

    _, run = kitti_run
    fuse_cfg = yaml.safe_load((REPO / "configs" / "kitti.yaml").read_text())["fuse"]
    assert "model" not in fuse_cfg.get("motion", {})
    fuse = RunDir(run).load()["stages"]["fuse"]
    assert fuse["config"]["fuse"]["motion"]["model"] == "auto"
    assert fuse["summary"]["vehicles"]["car"]["model"] == "constant_velocity"


def _truth(log: Path) -> PoseTable:
    recs = [
        r
        for r in LogSet([McapLogSource(log)], load_config().logs).records(roles=("ground_truth",))
        if isinstance(r, PoseRecord)
    ]
    return PoseTable(
        np.array([r.stamp_ns for r in recs]),
        np.array([r.p_m for r in recs]),
        np.array([r.q_xyzw for r in recs]),
    )


def test_kitti_estimate_follows_ground_truth(kitti_run):
    clip, run = kitti_run
    est = read_tum(run / "fuse" / "car.tum")
    gt = interpolate_positions(
        _truth(run / "car.mcap").stamps_ns, _truth(run / "car.mcap").p_nav_m, est.stamps_ns
    )
    assert len(est) == 51 and np.all(np.isfinite(gt))
    dist = float(np.sum(np.linalg.norm(np.diff(gt, axis=0), axis=1)))
    figures = {}
    for kind in ("none", "se3", "sim3"):
        al = umeyama(est.p_nav_m, gt, kind) if kind != "none" else None
        p = est.p_nav_m if al is None else al.apply(est.p_nav_m)
        e = np.linalg.norm(p - gt, axis=1)
        figures[kind] = (float(np.sqrt(np.mean(e**2))), 100.0 * e[-1] / dist, al)
    print(
        f"\nKITTI clip {clip}: {dist:.1f} m; ATE (no alignment) {figures['none'][0]:.2f} m, "
        f"final drift {figures['none'][1]:.2f} m per 100 m; SE3 ATE {figures['se3'][0]:.2f} m; "
        f"Sim3 ATE {figures['sim3'][0]:.2f} m (scale {figures['sim3'][2].scale:.3f})"
    )
    # The data README: judge clip a after SE3, clip b (calibration and ground truth disagree
    # in scale by 4-5 %) after Sim3 alignment.
    if clip == "a":
        # before the car's angular-acceleration noise in configs/kitti.yaml: 0.166 m, 2.9 %;
        # before its calibration pass and window 0.076 / 0.044 m, with them 0.043 / 0.034 m,
        # each pose written as the window last estimated it 0.042 / 0.029 m (issue 15 asks
        # 0.065 / 0.025)
        assert figures["se3"][0] < 0.065
        assert figures["sim3"][0] < 0.04
        assert figures["none"][1] < 1.5  # % of distance travelled
    else:
        assert figures["sim3"][0] < 0.25  # 0.286 m before configs/kitti.yaml's motion noise
        # with the right principal point the calibration pass finds (below), the scale
        # disagreement is gone: SE3 0.32 m (1.05 m with the rig as calibrated), scale 0.979
        assert figures["se3"][0] < 0.5
        assert 0.96 < figures["sim3"][2].scale < 1.02


# The batch solution's estimates of the right camera's principal point correction (`cvslam
# refine --config configs/kitti.yaml`, BENCHMARKS.md "Refine: the right camera's principal
# point"): an independent estimate from all the frames at once.
REFINE_RIGHT_CX_PX = {"a": (0.197, 0.015), "b": (0.909, 0.015)}


def test_kitti_calibration_pass_agrees_with_the_batch_solution(kitti_run):
    """configs/kitti.yaml's calibration pass (`rig_calibration.py`) estimates the right
    principal point in the filter: within three standard deviations (its own and the batch
    solution's) of what `cvslam refine` finds, and a twentieth of a pixel or better."""
    from cvslam_cli.io.rundir import RunDir

    clip, run = kitti_run
    est = RunDir(run).load()["stages"]["fuse"]["summary"]["right_cx_px"]["car"]
    ref, ref_std = REFINE_RIGHT_CX_PX[clip]
    print(f"\nKITTI clip {clip}: u0 {est['value']:+.3f} +- {est['std']:.3f} px (refine {ref:+.3f})")
    assert est["std"] < 0.05
    assert abs(est["value"] - ref) < 3 * np.hypot(est["std"], ref_std)
