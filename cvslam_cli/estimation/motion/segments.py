"""Motion samples between two frames: the pieces the motion model is stepped over."""

from __future__ import annotations

import numpy as np

from cvslam_cli.records.arrays import F64, I64


def motion_segments(stamps_ns: I64, inputs: F64, t0_ns: int, t1_ns: int) -> tuple[F64, F64]:
    """Inputs and durations (s) of the motion steps from t0 to t1: breakpoints at the
    samples in (t0, t1), each piece driven by the latest sample at or before its start
    (zero-order hold; the first sample before any). (U (k, d), dts (k,))."""
    if t1_ns <= t0_ns:
        return np.zeros((0, inputs.shape[1])), np.zeros(0)
    if len(stamps_ns) == 0:
        return np.zeros((1, inputs.shape[1])), np.array([(t1_ns - t0_ns) * 1e-9])
    lo = np.searchsorted(stamps_ns, t0_ns, side="right")
    hi = np.searchsorted(stamps_ns, t1_ns, side="left")
    knots = np.concatenate([[t0_ns], stamps_ns[lo:hi], [t1_ns]])
    src = np.maximum(np.arange(lo - 1, hi), 0)
    return inputs[src], np.diff(knots) * 1e-9
