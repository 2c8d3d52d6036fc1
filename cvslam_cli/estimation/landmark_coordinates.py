"""How a landmark is written in the filter state: Cartesian (the paper's) or anchored inverse
depth.

The paper puts each landmark in the state as its nav-frame position m (3 numbers). A point
triangulated from one stereo pair has a depth uncertainty of 10-25 % at the ranges a UAV
sees; its error is Gaussian in the inverse depth (the disparity), not in the depth, and the
observation model is far from linear along the ray over that range, so the filter's
attitude soon claims more than it knows (BENCHMARKS.md, "Fuse: consistency (issue 15)").
The standard cure (Civera, Davison & Montiel 2008; OpenVINS's anchored inverse depth) writes
the point relative to the camera that first saw it:

    theta = (alpha, beta, rho) = (c_x / c_z, c_y / c_z, 1 / c_z),  c: the point in the
                                                                    anchor's left camera
    m = p_a + C(Psi_a) (t_body_cam + R_cam_body^T (alpha, beta, 1) / rho)

The anchor (p_a, Psi_a) is a clone of the vehicle's pose when the landmark is created, kept
in the state (stochastic cloning; one clone for all the landmarks a vehicle starts in one
frame) and removed with its last landmark. For a rectified stereo pair theta is a linear
function of the measured (u_l, v_l, disparity), so the initial Gaussian is exact and
independent of the state (the clone carries the pose uncertainty). Keeping the anchor in the
state is what keeps the filter honest about what it cannot observe: moving the whole scene
(vehicles, anchors, and so the landmarks) by a translation, or turning it about the vertical,
leaves every predicted pixel unchanged at any linearisation point (`tests/estimation/
test_landmark_coordinates.py`), as with Cartesian points for a translation; an anchor held
fixed outside the state breaks that and the filter gains information about its absolute
position that no measurement carries.

Both kinds share one mechanism: a landmark's `size` numbers in the state (Cartesian: m;
anchored: anchor (6) then theta (3)) -> `to_nav` (m, d m / d params). Everything outside the
update sees nav-frame positions and covariances.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, Protocol

import numpy as np

from cvslam_cli.estimation.motion.models import inertial_team
from cvslam_cli.geometry.rotations import euler_zyx_matrices
from cvslam_cli.records.arrays import F64

CoordinatesName = Literal["cartesian", "inverse_depth"]
CoordinatesSetting = Literal["auto", "cartesian", "inverse_depth"]

# Inverse depths below this (points beyond 10^6 m, or moved through infinity by an update)
# are clipped in the conversion: such a point is at infinity along its ray.
MIN_INVERSE_DEPTH_PER_M = 1e-6


class LandmarkCoordinates(Protocol):
    """`size` numbers per landmark (its anchor's included); `anchored`: whether landmarks
    refer to an anchor clone in the state."""

    name: CoordinatesName
    size: int
    anchored: bool

    def to_nav(self, params: F64, R_cam_body: F64, t_body_cam: F64) -> tuple[F64, F64]:
        """params (k, size), the anchor camera's R_cam_body (k, 3, 3) and t_body_cam (k, 3)
        -> m (k, 3) and d m / d params (k, 3, size)."""
        ...


class Cartesian:
    """params = m (the paper's landmarks)."""

    name: CoordinatesName = "cartesian"
    size = 3
    anchored = False

    def to_nav(self, params: F64, R_cam_body: F64, t_body_cam: F64) -> tuple[F64, F64]:
        m = np.atleast_2d(params)
        return m, np.broadcast_to(np.eye(3), (len(m), 3, 3))  # identity: a read-only view


class AnchoredInverseDepth:
    """params = (p_a (3), Psi_a (3), alpha, beta, rho) (module docstring)."""

    name: CoordinatesName = "inverse_depth"
    size = 9
    anchored = True

    @staticmethod
    def from_camera(p_cam_m: F64) -> tuple[F64, F64]:
        """theta (k, 3) of points (k, 3) in the anchor's left camera frame, and
        d theta / d p_cam (k, 3, 3)."""
        c = np.atleast_2d(p_cam_m)
        x, y, z = c[:, 0], c[:, 1], c[:, 2]
        G = np.zeros((len(c), 3, 3))
        G[:, 0, 0] = G[:, 1, 1] = 1.0 / z
        G[:, 0, 2] = -x / z**2
        G[:, 1, 2] = -y / z**2
        G[:, 2, 2] = -1.0 / z**2
        return np.stack([x / z, y / z, 1.0 / z], axis=1), G

    @staticmethod
    def camera_point(theta: F64) -> tuple[F64, F64]:
        """The inverse of `from_camera`: c (k, 3) and d c / d theta (k, 3, 3)."""
        theta = np.atleast_2d(theta)
        a, b = theta[:, 0], theta[:, 1]
        r = np.maximum(theta[:, 2], MIN_INVERSE_DEPTH_PER_M)
        ray = np.stack([a, b, np.ones_like(a)], axis=1)
        D = np.zeros((len(theta), 3, 3))
        D[:, 0, 0] = D[:, 1, 1] = 1.0 / r
        D[:, :, 2] = -ray / r[:, None] ** 2
        return ray / r[:, None], D

    def from_nav(
        self, m_nav_m: F64, anchor: F64, R_cam_body: F64, t_body_cam: F64
    ) -> tuple[F64, F64, F64]:
        """theta (k, 3) of nav points m (k, 3) relative to the anchor pose (p_a, Psi_a)
        (6,) whose left camera is R_cam_body (3, 3), t_body_cam (3,); d theta / d m
        (k, 3, 3) and d theta / d anchor (k, 3, 6)."""
        m = np.atleast_2d(m_nav_m)
        C, dC = euler_zyx_matrices(anchor[3:6])
        C, dC = C[0], dC[0]
        w = m - anchor[:3]
        A = R_cam_body @ C.T  # d c / d m
        c = w @ A.T - R_cam_body @ t_body_cam
        theta, G = self.from_camera(c)
        J_m = G @ A
        J_a = np.empty((len(m), 3, 6))
        J_a[:, :, :3] = -J_m
        for i in range(3):  # d c / d Psi_a,i = R_cam_body dC_i^T w
            J_a[:, :, 3 + i] = np.einsum("kij,kj->ki", G, w @ (R_cam_body @ dC[i].T).T)
        return theta, J_m, J_a

    def to_nav(self, params: F64, R_cam_body: F64, t_body_cam: F64) -> tuple[F64, F64]:
        params = np.atleast_2d(params)
        c, D = self.camera_point(params[:, 6:9])
        R_body_cam = np.swapaxes(R_cam_body, 1, 2)
        b = t_body_cam + np.einsum("kij,kj->ki", R_body_cam, c)  # the point in the anchor body
        C, dC = euler_zyx_matrices(params[:, 3:6])
        m = params[:, :3] + np.einsum("kij,kj->ki", C, b)
        M = np.empty((len(params), 3, 9))
        M[:, :, :3] = np.eye(3)
        M[:, :, 3:6] = np.einsum("klij,kj->kil", dC, b)
        M[:, :, 6:9] = C @ R_body_cam @ D
        return m, M


def resolve(
    setting: CoordinatesSetting, motion_kinds: Sequence[str]
) -> tuple[CoordinatesName, str]:
    """The coordinates the setting fuse.map.landmark_coordinates gives a team whose vehicles
    have motion models `motion_kinds`, and why. auto: inverse depth when a vehicle has an
    IMU (`motion.models.inertial_team`: UAVs over ground far below, where it measured better
    in accuracy and consistency, for the ground robots of a team with UAVs too), else
    Cartesian (wheel odometry or none: ground vehicles alone, with forward cameras at short
    range, where the Cartesian point measured better; BENCHMARKS.md, "Fuse: consistency
    (issue 15)", "Fuse: a mixed team mapped the aerial way")."""
    if setting != "auto":
        return setting, "fuse.map.landmark_coordinates"
    if inertial_team(motion_kinds):
        return "inverse_depth", "auto: a vehicle has an IMU"
    return "cartesian", "auto: no vehicle has an IMU"


def coordinates(name: CoordinatesName) -> LandmarkCoordinates:
    """The parameterisation called `name`."""
    return {"cartesian": Cartesian, "inverse_depth": AnchoredInverseDepth}[name]()
