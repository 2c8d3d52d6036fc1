"""Motion samples between two frames: the pieces the motion model is stepped over.

An IMU (or odometry) sample is the rate at its stamp; between two samples the rate moves on.
Each piece is therefore driven by the samples' linear interpolation at its midpoint (for a
whole interval between two samples, their mean: OpenVINS's and VINS-Mono's discrete
propagation), not by the sample at its start held over it, whose error grows with the turn
rate (BENCHMARKS.md, "Fuse: the IMU between its samples"). The last piece before a frame
reads the first sample after it: a filter over a recorded log has it.
"""

from __future__ import annotations

import numpy as np

from cvslam_cli.records.arrays import F64, I64


def motion_segments(stamps_ns: I64, inputs: F64, t0_ns: int, t1_ns: int) -> tuple[F64, F64]:
    """Inputs and durations (s) of the motion steps from t0 to t1: breakpoints at the
    samples in (t0, t1), each piece driven by the samples (inputs (N, d) at stamps_ns (N,))
    interpolated linearly at its midpoint; before the first sample the first, after the last
    the last (module docstring). (U (k, d), dts (k,))."""
    if t1_ns <= t0_ns:
        return np.zeros((0, inputs.shape[1])), np.zeros(0)
    if len(stamps_ns) == 0:
        return np.zeros((1, inputs.shape[1])), np.array([(t1_ns - t0_ns) * 1e-9])
    lo = np.searchsorted(stamps_ns, t0_ns, side="right")
    hi = np.searchsorted(stamps_ns, t1_ns, side="left")
    knots = np.concatenate([[t0_ns], stamps_ns[lo:hi], [t1_ns]])
    # the samples around [t0, t1], on times relative to t0 (float64 keeps ns stamps exact)
    a, b = max(lo - 1, 0), min(hi + 1, len(stamps_ns))
    t_s = (stamps_ns[a:b] - t0_ns) * 1e-9
    mid_s = 0.5 * (knots[:-1] + knots[1:] - 2 * t0_ns) * 1e-9
    U = np.zeros((len(mid_s), inputs.shape[1]))
    for j in range(inputs.shape[1]):
        U[:, j] = np.interp(mid_s, t_s, inputs[a:b, j])
    return U, np.diff(knots) * 1e-9
