"""The stereo rig's right principal point, estimated (`motion/calibration.py`,
`observation.RightCxShift`, `rig_calibration.py`): the moved points are the rig's
re-triangulation and their Jacobians finite differences, the block with du predicts and
propagates like its motion model, and a calibration pass finds an offset a simulated rig was
recorded with and takes the error it caused away."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cvslam_cli.estimation.gauge import vehicle_basis
from cvslam_cli.estimation.motion.calibration import RIGHT_CX_STATE, RightCxCalibrated
from cvslam_cli.estimation.motion.ins import InsNoise
from cvslam_cli.estimation.motion.models import (
    ConstantVelocityModel,
    InitialUncertainty,
    InsModel,
    propagate,
)
from cvslam_cli.estimation.observation import RightCxShift, StereoObservationModel
from cvslam_cli.estimation.state import JointState
from cvslam_cli.estimation.vehicle import VehiclePose
from cvslam_cli.geometry.camera import stereo_rig
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.geometry.stereo import triangulate_matches
from cvslam_cli.io.features_file import load_features, save_features
from cvslam_cli.io.rundir import RunDir
from cvslam_cli.sim.scenario import SCENARIO_DIR, StereoRigSpec, load_scenario
from cvslam_cli.sim.stage import run as simulate
from cvslam_cli.sim.vehicles import build_rig
from tests.scenarios import small_uav_scenario

RIG = build_rig("t", StereoRigSpec(rectified=True, tilt_deg=5.0, lever_arm_m=(0.3, -0.1, 0.2)))
OBS = StereoObservationModel.from_rig(RIG)
INIT = InitialUncertainty(0.1, 0.01, 0.2, 0.05, 0.01, 0.001)


def _camera_points(n: int, rng: np.random.Generator) -> np.ndarray:
    return np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-5, 5, n), rng.uniform(5, 80, n)])


def _pixels(rig, p_cam: np.ndarray, right_cx_shift: float) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted left and right pixels of left-camera points, the right image taken by a
    camera whose principal point is right_cx_shift px further along x than the rig's."""
    T = np.linalg.inv(rig.T_left_right)
    p_r = p_cam @ T[:3, :3].T + T[:3, 3]
    Kl, Kr = rig.left.K, rig.right.K
    uv_l = (p_cam[:, :2] / p_cam[:, 2:]) @ np.diag([Kl[0, 0], Kl[1, 1]]) + Kl[:2, 2]
    uv_r = (p_r[:, :2] / p_r[:, 2:]) @ np.diag([Kr[0, 0], Kr[1, 1]]) + Kr[:2, 2]
    return uv_l, uv_r + np.array([right_cx_shift, 0.0])


def test_moved_points_are_the_rigs_triangulation_with_finite_difference_jacobians() -> None:
    """Points triangulated with the rig as calibrated, moved by du, are the triangulation with
    the right principal point at cx + du; their covariance is J C J^T, and dp'/du and J are
    finite differences; du = 0 leaves them."""
    rng = np.random.default_rng(3)
    p_true = _camera_points(30, rng)
    du = 0.7
    uv_l, uv_r = _pixels(RIG, p_true, du)  # the right image of a camera off by du
    p_cal, cov_cal, keep = triangulate_matches(RIG, uv_l, uv_r, 1e4, 0.5)
    assert keep.all()
    shift = RightCxShift(OBS.fx_baseline, du)
    p_moved, cov_moved, dp_du = shift.apply(p_cal, cov_cal)
    np.testing.assert_allclose(p_moved, p_true, rtol=1e-9, atol=1e-9)
    h = 1e-6
    fd = (RightCxShift(OBS.fx_baseline, du + h).apply(p_cal, cov_cal)[0] - p_moved) / h
    np.testing.assert_allclose(dp_du, fd, rtol=1e-5, atol=1e-8)
    J = np.empty((len(p_cal), 3, 3))  # dp'/dp by finite differences
    for k in range(3):
        e = np.zeros(3)
        e[k] = h * 10
        J[:, :, k] = (shift.apply(p_cal + e, cov_cal)[0] - p_moved) / (h * 10)
    np.testing.assert_allclose(cov_moved, J @ cov_cal @ np.swapaxes(J, 1, 2), rtol=1e-4)
    same, same_cov, _ = RightCxShift(OBS.fx_baseline, 0.0).apply(p_cal, cov_cal)
    np.testing.assert_array_equal(same, p_cal)
    np.testing.assert_allclose(same_cov, cov_cal, rtol=1e-15)


def test_the_model_with_a_right_cx_moves_the_right_column_only() -> None:
    p, euler = np.array([1.0, -2.0, -3.0]), np.array([0.05, -0.1, 0.7])
    m = p + _camera_points(12, np.random.default_rng(4)) @ euler_zyx_to_matrix(*euler).T
    z0 = OBS.project(p, euler, m)
    z1 = OBS.with_right_cx(0.4).project(p, euler, m)
    np.testing.assert_allclose(z1[:, 2], z0[:, 2] + 0.4, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(z1[:, [0, 1, 3]], z0[:, [0, 1, 3]])
    assert OBS.with_right_cx(0.0) is OBS and OBS.with_right_cx(0.4).rectified


@pytest.mark.parametrize(
    "motion",
    [InsModel(InsNoise(2e-3, 1.7e-4), biases=True), ConstantVelocityModel(0.5, 0.05)],
    ids=["ins", "cv"],
)
def test_the_block_with_du_propagates_its_motion_and_keeps_du(motion) -> None:
    """du is a constant of the log (F = 1, no noise) appended to the motion model's block;
    the pose, its Jacobian, the gauge and the state names read the motion states as before."""
    model = RightCxCalibrated(motion, 0.8)
    x_m = motion.initial_state(np.array([1.0, 2, -3]), np.array([0.1, -0.05, 0.9]),
                               np.array([2.0, 0.5, 0.0]), np.zeros(3))  # fmt: skip
    x = model.extend_state(x_m)
    x[-1] = 0.3
    U = np.tile([0.1, 0.0, -9.7, 0.01, 0.0, 0.02], (5, 1))[:, : motion.input_size]
    dts = np.full(5, 0.02)
    xm1, Fm, Qm = propagate(motion, x_m, U, dts)
    x1, F, Q = propagate(model, x, U, dts)
    np.testing.assert_allclose(x1[:-1], xm1, rtol=1e-12)
    assert x1[-1] == 0.3 and F[-1, -1] == 1.0 and not F[-1, :-1].any() and not F[:-1, -1].any()
    np.testing.assert_allclose(F[:-1, :-1], Fm, rtol=1e-12)
    np.testing.assert_allclose(Q[:-1, :-1], Qm, rtol=1e-12)
    assert not Q[-1].any()
    assert model.state_names[-1] == RIGHT_CX_STATE and model.n == motion.n + 1
    np.testing.assert_array_equal(model.pose_jacobian(x)[:, :-1], motion.pose_jacobian(x_m))
    assert not model.pose_jacobian(x)[:, -1].any()
    P0 = model.initial_covariance(INIT)
    assert P0[-1, -1] == pytest.approx(0.64) and not P0[-1, :-1].any()
    N = vehicle_basis(model, x, True)
    assert not N[-1].any()
    np.testing.assert_array_equal(N[:-1], vehicle_basis(motion, x_m, True))


class _Vehicle:
    name = "car"
    obs = OBS
    model = RightCxCalibrated(ConstantVelocityModel(0.5, 0.05), 1.0)
    right_cx_px = 0.25  # a correction already applied, du estimated on top of it


def _pose(du: float) -> VehiclePose:
    m = _Vehicle.model
    p0, e0 = np.array([0.5, -1.0, -2.0]), np.array([0.02, -0.03, 0.4])
    x = m.extend_state(m.motion.initial_state(p0, e0, np.ones(3), np.zeros(3)))
    x[-1] = du
    st = JointState([("car", m, x, m.initial_covariance(INIT))])
    return VehiclePose.of(st, _Vehicle())  # type: ignore[arg-type]


def test_the_pose_predicts_with_du_and_its_jacobians_are_finite_differences() -> None:
    """d z / d du (the vehicle's Jacobian) and d m / d du of a new landmark (through its moved
    camera point) equal finite differences; the frame's points move by the correction and the
    estimate together."""
    du, h = 0.3, 1e-6
    pose, pose_h = _pose(du), _pose(du + h)
    assert pose.right_cx_px == pytest.approx(0.55) and pose.right_cx_row == 12
    m = (
        pose.p_nav_m
        + _camera_points(8, np.random.default_rng(5)) @ euler_zyx_to_matrix(*pose.euler_rad).T
    )
    z, H_pose, _ = pose.obs.predict(pose.p_nav_m, pose.euler_rad, m)
    z_h = pose_h.obs.predict(pose.p_nav_m, pose.euler_rad, m)[0]
    H_v = pose.vehicle_jacobian(H_pose)
    np.testing.assert_allclose(H_v[:, :, 12], (z_h - z) / h, atol=1e-6)
    np.testing.assert_allclose(H_v[:, :, :12], H_pose @ pose.J[:, :12])
    # a new landmark from a camera point triangulated with the feature file's rig
    rng = np.random.default_rng(6)
    p_file = _camera_points(5, rng)
    cov = np.tile(np.eye(3) * 0.01, (5, 1, 1))
    p_cam, _, dp_du = pose.right_cx_shift().apply(p_file, cov)
    p_cam_h = pose_h.right_cx_shift().apply(p_file, cov)[0]
    mm, J_pose, J_pc = pose.obs.landmark_jacobians(pose.p_nav_m, pose.euler_rad, p_cam)
    mm_h = pose.obs.landmark_jacobians(pose.p_nav_m, pose.euler_rad, p_cam_h)[0]
    J_x = pose.point_jacobian(J_pose, J_pc, dp_du)
    np.testing.assert_allclose(J_x[:, :, 12], (mm_h - mm) / h, rtol=1e-5, atol=1e-7)


def _miscalibrated_yard(tmp_path: Path, offset_px: float) -> Path:
    """30 s of the yard's robot1 (landmark mode, seed 3) whose right camera imaged with its
    principal point offset_px further along x than the calibration the log records."""
    sc = load_scenario(SCENARIO_DIR / "ugv2_yard.yaml", ["mode=landmarks", "duration_s=30"], seed=3)
    out = simulate(sc, tmp_path / "yard").out_dir
    (out / "robot2.mcap").unlink()
    for f in (out / "features").glob("robot2*"):
        f.unlink()
    path = out / "features" / "robot1.npz"
    fs, meta = load_features(path)
    right = fs.right_uv_px.copy()
    right[:, 0] += offset_px
    p, cov, keep = triangulate_matches(
        stereo_rig(fs.rig), fs.left_uv_px[fs.match_left], right[fs.match_right], 1e4, 0.5
    )
    assert keep.all()
    save_features(
        dataclasses.replace(fs, right_uv_px=right, match_p_cam_m=p, match_cov_cam_m2=cov),
        path, meta,
    )  # fmt: skip
    return out


def _rmse(run: Path, stage: str = "fuse") -> float:
    return RunDir(run).load()["stages"][stage]["summary"]["vehicles"]["robot1"]["rmse_m"]


def test_a_calibration_pass_finds_the_offset_and_takes_its_error_away(tmp_path, cvslam) -> None:
    """A 0.5 px offset makes a 0.3 m-baseline robot's depths 2-12 % too long: its error over
    30 s is 0.68 m. The calibration pass finds the offset within four standard deviations
    (+0.466 +- 0.017 px) and the run with the rig corrected is within 0.1 m of the truth
    (0.05 m), its estimate recorded in run.yaml; `cvslam refine` starts from the corrected
    rig even where it does not estimate it itself (0.07 m; 0.49 m from the rig as
    calibrated)."""
    run = _miscalibrated_yard(tmp_path, 0.5)
    assert cvslam("-q", "fuse", run).code == 0
    uncorrected = _rmse(run)
    on = "fuse.calibration.estimate_right_cx=true"
    assert cvslam("-q", "fuse", run, "--force", "--set", on).code == 0
    fuse = RunDir(run).load()["stages"]["fuse"]
    est = fuse["summary"]["right_cx_px"]["robot1"]
    assert abs(est["value"] - 0.5) < 4 * est["std"] and est["std"] < 0.05
    assert uncorrected > 0.4 and _rmse(run) < 0.1
    assert cvslam("-q", "refine", run, "--set", "refine.reassociation.rounds=0").code == 0
    assert _rmse(run, "fuse_refined") < 0.15


def test_points_read_at_one_correction_move_on_to_another() -> None:
    """A frame's points moved to du1 as it is read, then to du2 once the update has moved the
    estimate (`FrameMatches.camera_points`), are the points moved to du2 at once."""
    from cvslam_cli.estimation.frame import FrameMatches

    rng = np.random.default_rng(8)
    p = _camera_points(6, rng)
    cov = np.tile(np.diag([0.01, 0.01, 0.2]), (6, 1, 1))
    first = RightCxShift(OBS.fx_baseline, 0.3)
    p1, cov1, dp1 = first.apply(p, cov)
    frame = FrameMatches(0, 0, np.zeros((6, 4)), np.zeros((6, 128), np.uint8), p1, cov1,
                         np.full(6, -1), np.full(6, 0.01), np.ones(6, bool), np.zeros(6, int),
                         dp1, first)  # fmt: skip
    rows = np.arange(6)
    same = frame.camera_points(rows, 0.3)
    assert same[0] is not None and np.array_equal(same[0], p1) and np.array_equal(same[2], dp1)
    p2, cov2, dp2 = frame.camera_points(rows, -0.45)
    q2, qcov2, qdp2 = RightCxShift(OBS.fx_baseline, -0.45).apply(p, cov)
    np.testing.assert_allclose(p2, q2, rtol=1e-12)
    np.testing.assert_allclose(cov2, qcov2, rtol=1e-9)
    np.testing.assert_allclose(dp2, qdp2, rtol=1e-12)


def test_a_rig_that_is_not_rectified_is_refused_in_one_line(tmp_path, cvslam) -> None:
    sc = load_scenario(
        small_uav_scenario(tmp_path),
        ["vehicles.uav1.camera.rectified=false", "mode=landmarks", "duration_s=2.0"],
    )
    run = simulate(sc, tmp_path / "nr").out_dir
    res = cvslam("fuse", run, "--set", "fuse.calibration.estimate_right_cx=true")
    assert res.code == 1
    line = res.err.strip().splitlines()[-1]
    assert "fuse.calibration.estimate_right_cx" in line and "uav1" in line
    assert "not rectified" in line and "Traceback" not in res.err
    assert not (run / "fuse").exists()


def test_only_the_vehicles_with_an_estimate_are_corrected() -> None:
    """A vehicle whose calibration pass diverged has no estimate: its rig stays as calibrated."""
    from types import SimpleNamespace

    from cvslam_cli.estimation.rig_calibration import RightCxEstimates

    def vehicle(name: str) -> SimpleNamespace:
        return SimpleNamespace(name=name, with_right_cx=lambda du: (name, du))

    est = RightCxEstimates({"a": (0.4, 0.02)}, {"b": "the calibration pass diverged"})
    a, b = vehicle("a"), vehicle("b")
    assert est.corrected([a, b]) == [("a", 0.4), b]  # type: ignore[list-item]
