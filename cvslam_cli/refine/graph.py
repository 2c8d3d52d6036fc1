"""The factor graph of a refinement (package docstring): built from a `RefineProblem`,
solved with GTSAM's Levenberg-Marquardt (sparse multifrontal Cholesky, METIS or COLAMD
ordering), and the marginal covariances of the solution (`marginals.py`).

Variables: x (pose, `gtsam.Pose3` = T_nav_body) per keyframe of every vehicle; with an IMU
also v (nav-frame velocity) and b (IMU biases); with the constant-velocity model v and w
(body rates); l (`gtsam.Point3`, nav) per landmark. Factors: two stereo reprojection
factors per observation (left and right camera, `GenericProjectionFactorCal3_S2` with the
camera's T_body_cam: eq. 19 for any rig, rectified or not), robust; motion factors
(`motion_factors.py`); priors on each vehicle's first keyframe from the filter's prior there
(pose; velocity, biases, body rates where the model has them): the gauge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.stats import chi2

from cvslam_cli.estimation.motion.segments import motion_segments
from cvslam_cli.geometry.rotations import euler_zyx_to_matrix
from cvslam_cli.records.arrays import F64
from cvslam_cli.refine import marginals
from cvslam_cli.refine.motion_factors import (
    TINY_VARIANCE,
    constant_velocity_factors,
    imu_factor,
    imu_params,
    odometry_factor,
)
from cvslam_cli.refine.pose_covariance import pose_cov_from_tangent, tangent_cov_from_pose
from cvslam_cli.refine.problem import (
    RefinedVehicle,
    RefineProblem,
    RefineResult,
    RefineSettings,
    RefineVehicle,
)

# an observation is counted an outlier at the solution beyond this (4 dof, both images)
OUTLIER_PROBABILITY = 0.999


def X(i: int) -> int:
    return gtsam.symbol("x", i)


def V(i: int) -> int:
    return gtsam.symbol("v", i)


def B(i: int) -> int:
    return gtsam.symbol("b", i)


def W(i: int) -> int:
    return gtsam.symbol("w", i)


def L(i: int) -> int:
    return gtsam.symbol("l", i)


@dataclass(frozen=True, eq=False)
class Graph:
    """The graph, its initial values, each vehicle's first pose index, the counts of
    factors by kind, and the reprojection factors' (observation, camera) order."""

    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    offsets: tuple[int, ...]
    factors: dict[str, int]


def _pose_prior_cov(vehicle: RefineVehicle, planar_sigma: float) -> F64:
    """(6, 6) covariance of (p, Psi) of the filter's prior at the first keyframe; a ground
    robot's height, roll and pitch (not states of its model) held by planar_sigma."""
    m = vehicle.model
    J = m.pose_jacobian(vehicle.x_first)
    cov = J @ vehicle.P_first @ J.T
    for k in range(6):
        if not np.any(J[k]):
            cov[k, k] += planar_sigma**2
    return cov


def _prior_pose(vehicle: RefineVehicle) -> F64:
    p, euler = vehicle.model.pose(vehicle.x_first)
    T = np.eye(4)
    T[:3, :3] = euler_zyx_to_matrix(*euler)
    T[:3, 3] = p
    return T


def _finite_difference_velocities(vehicle: RefineVehicle) -> F64:
    """(K, 3) nav-frame velocities of the initial poses (central differences)."""
    p = vehicle.T_nav_body[:, :3, 3]
    if len(p) < 2:
        return np.zeros_like(p)
    t = (vehicle.stamps_ns - vehicle.stamps_ns[0]) * 1e-9
    return np.gradient(p, t, axis=0)


def _body_rates(vehicle: RefineVehicle) -> F64:
    """(K, 3) body rates of the initial poses (forward differences, the last repeated)."""
    T = vehicle.T_nav_body
    K = len(T)
    w = np.zeros((K, 3))
    for k in range(K - 1):
        dt = (vehicle.stamps_ns[k + 1] - vehicle.stamps_ns[k]) * 1e-9
        w[k] = gtsam.Rot3.Logmap(gtsam.Rot3(T[k, :3, :3].T @ T[k + 1, :3, :3])) / dt
    if K > 1:
        w[-1] = w[-2]
    return w


def _add_vehicle(
    g: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    vehicle: RefineVehicle,
    o: int,
    settings: RefineSettings,
    counts: dict[str, int],
) -> None:
    """One vehicle's pose variables, prior and motion factors (keys offset by o)."""
    m = vehicle.model
    K = len(vehicle.stamps_ns)
    for k in range(K):
        values.insert(X(o + k), gtsam.Pose3(vehicle.T_nav_body[k]))
    T0 = _prior_pose(vehicle)
    cov0 = tangent_cov_from_pose(T0, _pose_prior_cov(vehicle, settings.planar_sigma))
    g.add(
        gtsam.PriorFactorPose3(
            X(o), gtsam.Pose3(T0), gtsam.noiseModel.Gaussian.Covariance(cov0 + TINY_VARIANCE)
        )
    )
    counts["prior"] += 1
    st, U = vehicle.motion_stamps_ns, vehicle.motion_inputs
    x0, P0 = vehicle.x_first, vehicle.P_first
    if m.kind == "ins":
        C0 = euler_zyx_to_matrix(*x0[6:9])
        vel = _finite_difference_velocities(vehicle)
        vel[0] = C0 @ x0[3:6]
        for k in range(K):
            values.insert(V(o + k), vel[k])
            values.insert(B(o + k), gtsam.imuBias.ConstantBias())
        cov_v = C0 @ P0[3:6, 3:6] @ C0.T
        g.add(gtsam.PriorFactorVector(V(o), vel[0], _gaussian(cov_v)))
        cov_b = P0[9:15, 9:15] if m.n == 15 else np.eye(6) * 1e-8
        bias0 = gtsam.imuBias.ConstantBias(
            *(x0[9:12], x0[12:15]) if m.n == 15 else (np.zeros(3), np.zeros(3))
        )
        g.add(gtsam.PriorFactorConstantBias(B(o), bias0, _gaussian(cov_b)))
        counts["prior"] += 2
        params = imu_params(m)  # type: ignore[arg-type]
        for k in range(K - 1):
            Uk, dts = motion_segments(
                st, U, int(vehicle.stamps_ns[k]), int(vehicle.stamps_ns[k + 1])
            )
            keys = (X(o + k), V(o + k), X(o + k + 1), V(o + k + 1), B(o + k), B(o + k + 1))
            g.add(imu_factor(params, Uk, dts, keys))
            counts["imu"] += 1
    elif m.kind == "odometry":
        for k in range(K - 1):
            Uk, dts = motion_segments(
                st, U, int(vehicle.stamps_ns[k]), int(vehicle.stamps_ns[k + 1])
            )
            g.add(
                odometry_factor(m, Uk, dts, (X(o + k), X(o + k + 1)), settings.planar_sigma)  # type: ignore[arg-type]
            )
            counts["odometry"] += 1
    else:  # constant velocity: nav velocity and body rates as variables
        vel = _finite_difference_velocities(vehicle)
        rates = _body_rates(vehicle)
        vel[0], rates[0] = x0[3:6], x0[9:12]
        for k in range(K):
            values.insert(V(o + k), vel[k])
            values.insert(W(o + k), rates[k])
        g.add(gtsam.PriorFactorVector(V(o), vel[0], _gaussian(P0[3:6, 3:6])))
        g.add(gtsam.PriorFactorVector(W(o), rates[0], _gaussian(P0[9:12, 9:12])))
        counts["prior"] += 2
        for k in range(K - 1):
            dt = (vehicle.stamps_ns[k + 1] - vehicle.stamps_ns[k]) * 1e-9
            keys = (X(o + k), V(o + k), W(o + k), X(o + k + 1), V(o + k + 1), W(o + k + 1))
            for f in constant_velocity_factors(m, dt, keys):  # type: ignore[arg-type]
                g.add(f)
            counts["constant_velocity"] += 2


def _gaussian(cov: F64) -> gtsam.noiseModel.Base:
    c = np.asarray(cov, dtype=float)
    return gtsam.noiseModel.Gaussian.Covariance(0.5 * (c + c.T) + np.eye(len(c)) * TINY_VARIANCE)


def pixel_noise(settings: RefineSettings) -> gtsam.noiseModel.Base:
    """The pixel noise of one camera's observation (2 numbers) under the robust kernel."""
    base = gtsam.noiseModel.Isotropic.Sigma(2, settings.pixel_sigma_px)
    if settings.robust == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    kernel = (est.Huber if settings.robust == "huber" else est.Cauchy).Create(settings.robust_k)
    return gtsam.noiseModel.Robust.Create(kernel, base)


def build(problem: RefineProblem, settings: RefineSettings) -> Graph:
    """The graph and initial values (module docstring)."""
    g = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    counts = {"prior": 0, "imu": 0, "odometry": 0, "constant_velocity": 0, "reprojection": 0}
    offsets = []
    o = 0
    for vehicle in problem.vehicles:
        offsets.append(o)
        _add_vehicle(g, values, vehicle, o, settings, counts)
        o += len(vehicle.stamps_ns)
    for j, p in enumerate(problem.p_nav_m):
        values.insert(L(j), gtsam.Point3(*p))
    noise = pixel_noise(settings)
    cams = [
        [
            (gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]), gtsam.Pose3(T))
            for K, T in zip(v.K_px, v.T_body_cam, strict=True)
        ]
        for v in problem.vehicles
    ]
    for v, k, j, z in zip(
        problem.obs_vehicle, problem.obs_keyframe, problem.obs_landmark, problem.z_px, strict=True
    ):
        xk, lk = X(offsets[v] + int(k)), L(int(j))
        for c, (cal, body_P_cam) in enumerate(cams[v]):
            g.add(
                gtsam.GenericProjectionFactorCal3_S2(
                    z[2 * c : 2 * c + 2], noise, xk, lk, cal, False, False, body_P_cam
                )
            )
        counts["reprojection"] += 2
    return Graph(g, values, tuple(offsets), counts)


def solve(
    graph: Graph,
    settings: RefineSettings,
    progress: Callable[[int, float], None] | None = None,
) -> tuple[gtsam.Values, float, float, int]:
    """(solution, initial error, final error, iterations): Levenberg-Marquardt until the
    error decreases by less than `relative_error_tol` of itself or `max_iterations`."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.max_iterations)
    params.setRelativeErrorTol(settings.relative_error_tol)
    params.setOrderingType(settings.ordering.upper())
    opt = gtsam.LevenbergMarquardtOptimizer(graph.graph, graph.initial, params)
    error0 = graph.graph.error(graph.initial)
    prev = error0
    it = 0
    while it < settings.max_iterations:
        opt.iterate()
        it += 1
        cur = opt.error()
        if progress is not None:
            progress(it, cur)
        if prev - cur <= settings.relative_error_tol * prev:
            break
        prev = cur
    return opt.values(), error0, opt.error(), it


def result(
    problem: RefineProblem, graph: Graph, values: gtsam.Values, settings: RefineSettings,
    error0: float, error1: float, iterations: int,
    progress: Callable[[int], None] | None = None,
) -> RefineResult:  # fmt: skip
    """The solution with its marginal covariances (poses in cvslam's (p, Psi) convention);
    `progress(k)`: k more variables' marginals done."""
    factorised = marginals.factorise(graph.graph, values)
    n_l = len(problem.landmark_id)
    pose_keys = [
        X(o + k) for v, o in zip(problem.vehicles, graph.offsets, strict=True)
        for k in range(len(v.stamps_ns))
    ]  # fmt: skip
    landmark_keys = [L(j) for j in range(n_l)] if settings.landmark_covariances else []
    tangents, lm_cov = factorised.poses_and_landmarks(pose_keys, landmark_keys, progress)
    vehicles = []
    first = 0
    for v, o in zip(problem.vehicles, graph.offsets, strict=True):
        K = len(v.stamps_ns)
        T = np.array([values.atPose3(X(o + k)).matrix() for k in range(K)]).reshape(K, 4, 4)
        tangent = tangents[first : first + K]
        first += K
        cov = np.array([pose_cov_from_tangent(T[k], tangent[k]) for k in range(K)])
        cov = cov.reshape(K, 6, 6)
        J = v.model.pose_jacobian(v.x_first)
        absent = ~np.any(J, axis=1)  # a ground robot's height, roll, pitch: not estimated
        cov[:, absent, :] = 0.0
        cov[:, :, absent] = 0.0
        vehicles.append(RefinedVehicle(v.name, v.stamps_ns.copy(), T, cov))
    p = np.array([values.atPoint3(L(j)) for j in range(n_l)]).reshape(n_l, 3)
    if not landmark_keys:
        lm_cov = np.full((n_l, 3, 3), np.nan)
    return RefineResult(
        tuple(vehicles), p, lm_cov, error0, error1, iterations, dict(graph.factors),
        _outliers(problem, graph, values, settings),
    )  # fmt: skip


def residuals_px(problem: RefineProblem, graph: Graph, values: gtsam.Values) -> F64:
    """(N, 4) reprojection residuals (u_l, v_l, u_r, v_r) in pixels of every observation at
    `values` (the reprojection factors follow the motion factors and priors in the graph)."""
    n = graph.factors["reprojection"]
    n_prior = graph.graph.size() - n
    r = np.zeros((len(problem.z_px), 4))
    for i in range(n):
        r[i // 2, 2 * (i % 2) : 2 * (i % 2) + 2] = graph.graph.at(n_prior + i).unwhitenedError(
            values
        )
    return r


def residual_scale_px(r_px: F64) -> float:
    """A robust standard deviation of the pixel residuals r_px (N, 4): 1.4826 times the
    median absolute residual (the Gaussian's, unmoved by a few wrong matches); nan if none."""
    return float(1.4826 * np.median(np.abs(r_px))) if r_px.size else float("nan")


def warm_start(graph: Graph, values: gtsam.Values, landmarks: bool = False) -> None:
    """Replace the vehicle states' initial values of `graph` (poses, velocities, biases,
    body rates) by those of an earlier solution `values` of a graph over the same vehicles
    and keyframes; the landmarks' too when `landmarks` (a graph of the same landmarks: the
    landmark keys of different re-association rounds' graphs differ)."""
    keys = graph.initial.keys()
    for key in keys:
        sym = chr(gtsam.Symbol(key).chr())
        if (sym == "l" and not landmarks) or not values.exists(key):
            continue
        if sym == "l":
            graph.initial.update(key, values.atPoint3(key))
        elif sym == "x":
            graph.initial.update(key, values.atPose3(key))
        elif sym == "b":
            graph.initial.update(key, values.atConstantBias(key))
        else:
            graph.initial.update(key, values.atVector(key))


def _outliers(
    problem: RefineProblem, graph: Graph, values: gtsam.Values, settings: RefineSettings
) -> int:
    """Observations whose reprojection residual (both images, 4 dof, in pixel sigmas) is
    beyond the OUTLIER_PROBABILITY chi-square bound at the solution."""
    limit = chi2.ppf(OUTLIER_PROBABILITY, 4)
    r = residuals_px(problem, graph, values) / settings.pixel_sigma_px
    return int(np.sum(np.sum(r**2, axis=1) > limit))
