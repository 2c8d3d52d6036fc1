"""Re-associate and solve, in rounds (docs/refine.md): round 1 associates around the
filter's estimate (pixel gate `gate_px`), each later round around the previous solution
with the chi-square gate chi2_4(gate_probability) in units of the residuals' robust scale
there (at least the pixel noise); every filter observation is gated there too. A final
check removes the observations of the last solution outside that gate and solves once more
from it (warm start): what the robust kernel only down-weighted is gone from the graph.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from scipy.stats import chi2

from cvslam_cli.records.arrays import F64, I64, U8
from cvslam_cli.refine import graph
from cvslam_cli.refine.keyframe_features import KeyframeFeatures
from cvslam_cli.refine.problem import RefineProblem, RefineSettings
from cvslam_cli.refine.reassociation import (
    NEW_POINT,
    Observed,
    Points,
    ProblemRows,
    ReassociationSettings,
    associate,
    problem_of,
    update_points,
)

# (problem, warm start or None) -> (graph, solution, error before, error after, iterations)
Solver = Callable[
    [RefineProblem, gtsam.Values | None], tuple[graph.Graph, gtsam.Values, float, float, int]
]


@dataclass(frozen=True)
class RoundStats:
    """One solve: observations and landmarks in its graph (new points from tracks among
    them), the filter's observations kept, the gate it was associated with (px radius over
    the 4 coordinates), iterations, error after, residual scale at its solution (px)."""

    observations: int
    landmarks: int
    new_points: int
    filter_observations: int
    gate_px: float
    iterations: int
    final_error: float
    residual_scale_px: float


@dataclass(frozen=True, eq=False)
class RoundsResult:
    """The last solve (problem, graph, solution, first round's initial error, last error,
    iterations in all), the simulator id and a descriptor (the first it was matched with)
    of each of its landmarks, (L,) and (L, D), the stats of each solve (the final check's
    last), and the observations the final check removed."""

    problem: RefineProblem
    graph: graph.Graph
    values: gtsam.Values
    initial_error: float
    final_error: float
    iterations: int
    true_id: I64
    descriptor: U8
    rounds: tuple[RoundStats, ...]
    removed: int


def _solution(
    problem: RefineProblem, g: graph.Graph, values: gtsam.Values
) -> tuple[list[F64], F64]:
    poses, o = [], 0
    for v in problem.vehicles:
        K = len(v.stamps_ns)
        poses.append(
            np.array([values.atPose3(graph.X(o + k)).matrix() for k in range(K)]).reshape(K, 4, 4)
        )
        o += K
    n = len(problem.landmark_id)
    p = np.array([values.atPoint3(graph.L(j)) for j in range(n)]).reshape(n, 3)
    return poses, p


def run_rounds(
    problem0: RefineProblem,
    features: Sequence[KeyframeFeatures],
    points: Points,
    base: Observed,
    settings: RefineSettings,
    rs: ReassociationSettings,
    next_id: int,
    solve: Solver,
    log: Callable[[str], None] = lambda _: None,
) -> RoundsResult:
    """`rs.rounds` (>= 1) rounds from the filter's problem `problem0` (its vehicles and
    initial poses), the points and base observations of `build.reassociation_start`; new
    points take ids from next_id."""
    vehicles = problem0.vehicles
    poses = [v.T_nav_body for v in vehicles]
    radius = rs.gate_px
    k2 = float(chi2.ppf(rs.gate_probability, 4))
    stats: list[RoundStats] = []
    e_first, iterations, warm = float("nan"), 0, None
    for r in range(rs.rounds):
        points, obs = associate(vehicles, poses, features, points, base, radius, r > 0, rs)
        problem, rows = problem_of(vehicles, poses, points, obs, next_id)
        g, values, e0, e1, it = solve(problem, warm)
        e_first = e0 if r == 0 else e_first
        iterations += it
        res = graph.residuals_px(problem, g, values)
        scale = graph.residual_scale_px(res)
        stats.append(_stats(problem, points, rows, obs, radius, it, e1, scale))
        log(
            f"refine: round {r + 1}: {len(problem.z_px)} observations "
            f"({stats[-1].filter_observations} the filter's), {len(problem.landmark_id)} landmarks "
            f"({stats[-1].new_points} from tracks), gate {radius:.3g} px; error {e1:.6g}, "
            f"residual scale {scale:.3g} px"
        )
        poses, p = _solution(problem, g, values)
        radius = float(np.sqrt(k2) * max(settings.pixel_sigma_px, scale))
        warm = values
        solved = np.array(points.p_nav_m, copy=True)
        solved[rows.points] = p
        last = (problem, rows, obs, g, values, res, e1, dataclasses.replace(points, p_nav_m=solved))
        points = update_points(points, rows, p, obs, features, rs.max_descriptors)
    problem, rows, obs, g, values, res, e1, pts = last
    inside = np.sum(res**2, axis=1) < radius**2
    removed = int(np.sum(~inside))
    if removed:
        keep = rows.observed[inside]
        problem, rows = problem_of(vehicles, poses, pts, obs.take(keep), next_id)
        # the solution's poses and landmark positions start the check's graph
        g, values, _, e1, it = solve(problem, warm)
        iterations += it
        scale = graph.residual_scale_px(graph.residuals_px(problem, g, values))
        stats.append(_stats(problem, pts, rows, obs.take(keep), radius, it, e1, scale))
        log(f"refine: final check: {removed} observations beyond the gate removed; error {e1:.6g}")
    return RoundsResult(
        problem, g, values, e_first, e1, iterations, pts.true_id[rows.points],
        pts.desc[rows.points, 0], tuple(stats), removed,
    )  # fmt: skip


def _stats(
    problem: RefineProblem, points: Points, rows: ProblemRows, obs: Observed, radius: float,
    it: int, e1: float, scale: float,
) -> RoundStats:  # fmt: skip
    return RoundStats(
        observations=len(problem.z_px),
        landmarks=len(problem.landmark_id),
        new_points=int(np.sum(points.landmark_id[rows.points] == NEW_POINT)),
        filter_observations=int(np.sum(obs.base[rows.observed])),
        gate_px=float(radius),
        iterations=it,
        final_error=float(e1),
        residual_scale_px=float(scale),
    )
