"""Localisation in the map from one stereo frame (unknown initial pose): PnP + RANSAC on
descriptor pairs finds the body pose through the camera mounting, rejects wrong pairs, and
gives up when too few landmarks agree."""

from __future__ import annotations

import numpy as np
import pytest

from cvslam_cli.estimation.localise import body_pose_from_camera, descriptor_pairs, localise
from cvslam_cli.estimation.observation import StereoObservationModel
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.sim.scenario import StereoRigSpec
from cvslam_cli.sim.vehicles import build_rig

P_TRUE = np.array([40.0, -25.0, -100.0])
EULER_TRUE = np.array([0.03, -0.02, 2.4])


@pytest.fixture(params=["down", "forward"])
def obs(request) -> StereoObservationModel:
    spec = StereoRigSpec(mount=request.param, tilt_deg=5.0, lever_arm_m=(0.3, -0.1, 0.2))
    return StereoObservationModel.from_rig(build_rig("t", spec))


def _scene(obs: StereoObservationModel, n: int, rng: np.random.Generator):
    """n landmarks in view of the left camera at the true pose, 30-120 m away."""
    R_cb, t_bc = obs.R_cam_body[0], obs.t_body_cam[0]
    K = obs.K[0]
    uv = np.column_stack(
        [rng.uniform(20, 2 * K[0, 2] - 20, n), rng.uniform(20, 2 * K[1, 2] - 20, n)]
    )
    depth = rng.uniform(30, 120, n)
    p_cam = np.column_stack(
        [(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(n)]
    )
    p_cam *= depth[:, None]
    C = euler_zyx_to_matrix(*EULER_TRUE)
    m = (p_cam @ R_cb + t_bc) @ C.T + P_TRUE
    z, _, _ = obs.predict(P_TRUE, EULER_TRUE, m)
    return m, z


def test_body_pose_from_camera_inverts_the_observation_model(obs):
    C = euler_zyx_to_matrix(*EULER_TRUE)
    R_cam_nav = obs.R_cam_body[0] @ C.T
    t = -R_cam_nav @ P_TRUE - obs.R_cam_body[0] @ obs.t_body_cam[0]
    p, euler = body_pose_from_camera(obs, R_cam_nav, t)
    np.testing.assert_allclose(p, P_TRUE, atol=1e-9)
    np.testing.assert_allclose(euler, EULER_TRUE, atol=1e-12)


def test_descriptor_pairs_ratio_test_and_one_match_per_landmark():
    rng = np.random.default_rng(0)
    desc_map = rng.integers(0, 256, (50, 128)).astype(np.uint8)
    obs = desc_map[[3, 7, 7, 20]].astype(int) + rng.integers(-3, 4, (4, 128))
    obs[2] += 20  # a worse copy of landmark 7
    ambiguous = ((desc_map[10].astype(int) + desc_map[11]) // 2)[None]  # between two
    desc_obs = np.clip(np.vstack([obs, ambiguous]), 0, 255).astype(np.uint8)
    rows, lm = descriptor_pairs(desc_obs, desc_map, ratio=0.8, max_distance=1e9)
    assert dict(zip(rows.tolist(), lm.tolist(), strict=True)) == {0: 3, 1: 7, 3: 20}


def test_localise_finds_the_pose_among_wrong_pairs(obs):
    rng = np.random.default_rng(1)
    m, z = _scene(obs, 60, rng)
    z = z + rng.normal(0, 0.3, z.shape)
    desc = rng.integers(0, 256, (60, 128)).astype(np.uint8)
    # 20 of the frame's matches are other points whose descriptors look like landmarks'
    wrong = rng.choice(60, 20, replace=False)
    z_wrong = z[wrong] + rng.uniform(-150, 150, (20, 1)) * np.array([1.0, 1.0, 1.0, 1.0])
    z_obs = np.vstack([z[:40], z_wrong[:, :]])
    desc_obs = np.vstack([desc[:40], desc[wrong]])
    # the map holds the 60 landmarks plus 100 others
    m_map = np.vstack([m, m[:1] + rng.normal(0, 50, (100, 3))])
    desc_map = np.vstack([desc, rng.integers(0, 256, (100, 128)).astype(np.uint8)])
    loc = localise(obs, z_obs, desc_obs, m_map, desc_map, ratio=0.8,
                   max_descriptor_distance=1e9, reprojection_px=2.0, min_inliers=12)  # fmt: skip
    assert loc is not None
    np.testing.assert_allclose(loc.p_nav_m, P_TRUE, atol=0.5)
    np.testing.assert_allclose(loc.euler_rad, EULER_TRUE, atol=5e-3)
    # every inlier is a right pair: frame row i < 40 is landmark i
    assert np.all(loc.match_rows < 40) and np.all(loc.landmark_rows == loc.match_rows)
    assert len(loc.match_rows) >= 35 and loc.rms_px < 1.0


def test_localise_gives_up_with_too_few_landmarks(obs):
    rng = np.random.default_rng(2)
    m, z = _scene(obs, 10, rng)
    desc = rng.integers(0, 256, (10, 128)).astype(np.uint8)
    kw = dict(ratio=0.8, max_descriptor_distance=1e9, reprojection_px=2.0)
    assert localise(obs, z, desc, m, desc, min_inliers=12, **kw) is None
    found = localise(obs, z, desc, m, desc, min_inliers=8, **kw)
    assert found is not None and len(found.match_rows) == 10
    # all pairs wrong: nothing agrees
    assert localise(obs, z[::-1], desc, m, desc, min_inliers=6, **kw) is None
