"""`make bench`: can a UAV's view and a ground robot's view of the same yard share landmarks
in images? The choice behind `configs/scenarios/mixed_yard.yaml` (BENCHMARKS.md, "Fuse: a
mixed team (issue 20)").

The yard of `mixed_yard` (seed 1); the robot's left camera of the scenario at five poses in
its lane, and a UAV above it (same heading) with either the scenario's camera (forward,
pitched 35 deg down, 8 m up) or a nadir camera (10 m up, like the paper's UAVs but lower).
OpenCV SIFT on both rendered left images, each robot keypoint matched to its nearest UAV
keypoint with the ratio test (0.8) and the filter's largest descriptor distance (350), with no
geometric prior (the filter's association gates by the predicted pixel as well, so it
rejects more of the wrong ones). A match is right when the rendered surface points behind
the two keypoints are within 0.15 m of each other. Printed per design; asserted: the
scenario's design gives right matches and more than the nadir one.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from cvslam_cli.geometry.rotations import euler_zyx_to_matrix, make_T
from cvslam_cli.sim.scenario import SCENARIO_DIR, load_scenario
from cvslam_cli.sim.stage import build_world
from cvslam_cli.sim.vehicles import build_rig
from cvslam_cli.sim.yard import render_yard_view

POSES = [(-20.0, -18.0, 0.0), (-20.0, 0.0, 0.0), (20.0, 18.0, np.pi), (0.0, 20.0, -np.pi / 2)]
POSES += [(-8.0, -20.0, 0.0)]


def _matches(world, rob_rig, uav_rig, altitude_m: float) -> tuple[int, int]:
    sift = cv2.SIFT_create(nfeatures=1500)
    right = wrong = 0
    for n, e, yaw in POSES:
        views = []
        for rig, down_m in ((rob_rig, 0.0), (uav_rig, altitude_m)):
            T_nav_body = make_T(euler_zyx_to_matrix(0.0, 0.0, yaw), np.array([n, e, -down_m]))
            view = render_yard_view(
                world, rig.left, T_nav_body @ rig.left.T_body_cam, want_points=True
            )
            img = np.clip(np.rint(view.radiance * 255), 0, 255).astype(np.uint8)
            kp, desc = sift.detectAndCompute(img, None)
            views.append((view, kp, desc))
        (vr, kr, dr), (vu, ku, du) = views
        for pair in cv2.BFMatcher().knnMatch(dr, du, k=2):
            if len(pair) < 2 or pair[0].distance > min(0.8 * pair[1].distance, 350.0):
                continue
            ur, uu = kr[pair[0].queryIdx].pt, ku[pair[0].trainIdx].pt
            pr = vr.p_nav_m[round(ur[1]), round(ur[0])]
            pu = vu.p_nav_m[round(uu[1]), round(uu[0])]
            if np.all(np.isfinite(pr)) and np.all(np.isfinite(pu)):
                if np.linalg.norm(pr - pu) < 0.15:
                    right += 1
                else:
                    wrong += 1
    return right, wrong


def test_uav_and_robot_views_share_features() -> None:
    sc = load_scenario(SCENARIO_DIR / "mixed_yard.yaml")
    world = build_world(sc)
    robot = build_rig("robot1", sc.vehicles["robot1"].camera)
    uav_cam = sc.vehicles["uav1"].camera
    designs = {
        "scenario: forward, pitched 35 deg down, 8 m": (build_rig("uav1", uav_cam), 8.0),
        "nadir, 10 m": (build_rig("uav1", replace(uav_cam, mount="down", tilt_deg=0.0)), 10.0),
    }
    found = {}
    print(f"\n{'UAV camera':45s} | right | wrong  (SIFT ratio-test matches, {len(POSES)} pairs)")
    for name, (rig, alt) in designs.items():
        found[name] = _matches(world, robot, rig, alt)
        print(f"{name:45s} | {found[name][0]:5d} | {found[name][1]:5d}")
    scenario, nadir = found.values()
    assert scenario[0] > 2 * nadir[0] and scenario[0] >= 20
