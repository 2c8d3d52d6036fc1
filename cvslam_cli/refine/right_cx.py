"""Each rig's right-camera principal point u0, from the motion (`refine.estimate_right_cx`).

A stereo rig's calibration fixes the right camera's u0; an error there is, on a rectified
pair, the same error in every disparity, and no single stereo frame can tell it from depth
(a point's depth fb / d absorbs it: near points hardly, far points by up to several per
cent). Across frames it can be told: the motion the near points and the far points give
agrees only at the right u0. KITTI's clips read it (BENCHMARKS.md, "Refine: the right
camera's principal point"): translations from stereo points of 8-12 px disparity are 2.5 %
longer than the true ones on clip a, from 40-70 px equal to them.

The correction c (px, one per vehicle's rig, prior N(0, sigma^2) around the calibration) is
estimated on the profile of the graph's error, E(c) = min over every other variable of the
error with the right camera's u0 moved by c (plus the prior's 0.5 (c / sigma)^2): Newton
steps c <- c - E'(c) / E''(c) from central differences of E over three warm-started solves
(c - h, c, c + h), one vehicle at a time, until a step is below a tenth of the estimate's
standard deviation 1 / sqrt(E''(c)) (E is half the chi-square). The solves are the
refinement's own graph with GTSAM's built-in factors: a variable u0 would need a Python
factor per right-camera observation, and GTSAM's Python factors receive a copy of every
value of the graph at every call (KITTI clip a: 0.65 ms a call; the refinement took 160 s
instead of 4.5 s).
The solution keeps c at its estimate: the poses' and landmarks' marginals leave out its
uncertainty (KITTI: +-0.015 px, a 1e-3 relative depth error at 15 px disparity).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cvslam_cli.records.arrays import F64
from cvslam_cli.refine.problem import RefineProblem

# (problem, start: an earlier solution's values or None, whether they are of a problem with
# the same landmarks (which then start from them too)) -> (solution, its values, its error):
# one solve of the refinement's graph
ProfileSolve = Callable[[RefineProblem, Any, bool], tuple[Any, Any, float]]

STEP_PX = 0.1  # h of the central differences
MAX_STEPS = 6


@dataclass(frozen=True, eq=False)
class RightCx:
    """problem: the input problem with each vehicle's right-camera u0 moved by c_px (V,)
    (from the calibration: the input's own correction included); std_px (V,) the standard
    deviation of each c; solution and error: the solve's solution at c_px and its error
    (the prior's term included); solves: the solves made."""

    problem: RefineProblem
    c_px: F64
    std_px: F64
    solution: Any
    error: float
    solves: int


def moved(problem: RefineProblem, dc_px: F64) -> RefineProblem:
    """`problem` with each vehicle's right-camera u0 moved by dc_px (V,)."""
    vehicles = []
    for v, dc in zip(problem.vehicles, dc_px, strict=True):
        K = v.K_px.copy()
        K[1, 0, 2] += dc
        vehicles.append(dataclasses.replace(v, K_px=K))
    return dataclasses.replace(problem, vehicles=tuple(vehicles))


def estimate(
    problem: RefineProblem,
    solve: ProfileSolve,
    prior_sigma_px: float,
    c0_px: F64 | None = None,
    warm: Any = None,
    warm_landmarks: bool = False,
) -> RightCx:
    """The corrections c on the profile of the graph's error (module docstring), from
    `problem`, whose right cameras are already moved by c0_px (V,) (default 0) from the
    calibration the prior is centred on; `warm`: the values of an earlier solution to start
    from (of the same landmarks when `warm_landmarks`)."""
    n = len(problem.vehicles)
    c = np.zeros(n) if c0_px is None else np.asarray(c0_px, dtype=float).copy()
    base = moved(problem, -c)  # the calibration's own u0

    def total(start: Any, c_px: F64, same: bool = True) -> tuple[Any, Any, float]:
        sol, values, error = solve(moved(base, c_px), start, same)
        return sol, values, error + 0.5 * float(np.sum((c_px / prior_sigma_px) ** 2))

    solution, values, e = total(warm, c, warm_landmarks)
    solves = 1
    std = np.full(n, prior_sigma_px)
    for _ in range(MAX_STEPS):
        step = np.zeros(n)
        for v in range(n):
            h = np.zeros(n)
            h[v] = STEP_PX
            e_plus = total(values, c + h)[2]
            e_minus = total(values, c - h)[2]
            solves += 2
            curvature = (e_plus - 2.0 * e + e_minus) / STEP_PX**2
            if curvature <= 1.0 / prior_sigma_px**2:  # no more than the prior: numerical noise
                std[v] = prior_sigma_px
                continue
            step[v] = -(e_plus - e_minus) / (2.0 * STEP_PX) / curvature
            std[v] = 1.0 / np.sqrt(curvature)
        c = c + step
        solution, values, e = total(values, c)
        solves += 1
        if np.all(np.abs(step) < 0.1 * std):
            break
    return RightCx(moved(base, c), c, std, solution, e, solves)
