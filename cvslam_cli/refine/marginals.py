"""Marginal covariances of a refined solution: blocks of the inverse of the graph's
information matrix H = A^T A at the solution (A the whitened sparse Jacobian GTSAM
linearises), from one sparse factorisation.

Why not `gtsam.Marginals`: its Cholesky declares a clique indeterminate when the last two
pivots of its frontal variables differ by more than 2^12 (`choleskyPartial`), a test on the
unscaled pivots. The graph's units put IMU gyro-bias information (~5e10, a random walk of
2e-5 rad/s per sqrt(s) between keyframes 0.1 s apart) beside landmark information (~1 for a
far point): on the `uav2_paper` images mission the two-UAV graph at its solution fails that
test under either ordering (COLAMD, METIS), while the same matrix Jacobi-scaled has its
smallest pivot at 1e-8: determinate. So the matrix is scaled, S = D^-1/2 H D^-1/2 with D
its diagonal (exact: Sigma = D^-1/2 S^-1 D^-1/2), factorised once with SuperLU (a symmetric
minimum-degree ordering, no pivoting: S is positive definite), and solved for the requested
variables' columns a batch at a time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from cvslam_cli.records.arrays import F64

# right-hand sides per solve (the batch's dense block is (n, BATCH_COLUMNS))
BATCH_COLUMNS = 256
# a pivot of the scaled matrix below this is a direction nothing constrains (an exactly
# singular matrix leaves round-off, ~1e-16; the two-UAV mission's smallest is 1e-8)
MIN_PIVOT = 1e-12


class IndeterminateError(ValueError):
    """The information matrix is singular at the solution (a variable nothing constrains)."""


@dataclass(frozen=True, eq=False)
class Factorisation:
    """The scaled information matrix S = D^-1/2 H D^-1/2 factorised (`lu`), `scale` (n,) =
    D^-1/2, and each key's first column and tangent dimension."""

    lu: sla.SuperLU
    scale: F64
    offset: dict[int, int]
    dim: dict[int, int]

    def covariances(
        self, keys: Sequence[int], progress: Callable[[int], None] | None = None
    ) -> F64:
        """(len(keys), d, d) marginal covariance of each key (all of one tangent dimension
        d); `progress(k)`: k more keys done."""
        if not keys:
            return np.zeros((0, 0, 0))
        dims = {self.dim[k] for k in keys}
        if len(dims) > 1:
            raise ValueError("Factorisation.covariances: the keys must share one dimension")
        d = dims.pop()
        first = np.array([self.offset[k] for k in keys], dtype=np.int64)
        columns = (first[:, None] + np.arange(d)).ravel()
        out = np.empty((len(keys), d, d))
        per_batch = max(1, BATCH_COLUMNS // d)
        for i in range(0, len(keys), per_batch):
            cols = columns[i * d : (i + per_batch) * d]
            rhs = np.zeros((len(self.scale), len(cols)))
            rhs[cols, np.arange(len(cols))] = 1.0
            block = self.lu.solve(rhs)[cols] * np.outer(self.scale[cols], self.scale[cols])
            m = len(cols) // d
            blocks = block.reshape(m, d, m, d)[np.arange(m), :, np.arange(m), :]
            out[i : i + m] = 0.5 * (blocks + blocks.transpose(0, 2, 1))
            if progress is not None:
                progress(m)
        return out


def factorise(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> Factorisation:
    """The information matrix of `graph` at `values`, scaled and factorised;
    IndeterminateError if it is singular there."""
    H, offset, dim = _information(graph, values)
    diagonal = H.diagonal()
    if np.min(diagonal) <= 0.0:
        raise IndeterminateError("a variable has no information at the solution")
    scale = 1.0 / np.sqrt(diagonal)
    S = sp.diags(scale) @ H @ sp.diags(scale)
    try:
        lu = sla.splu(
            S.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )  # fmt: skip
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise IndeterminateError("the information matrix is singular at the solution") from exc
    pivots = lu.U.diagonal()
    if not np.all(np.isfinite(pivots)) or np.min(pivots) < MIN_PIVOT:
        raise IndeterminateError("the information matrix is singular at the solution")
    return Factorisation(lu, scale, offset, dim)


def _information(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
) -> tuple[sp.csr_matrix, dict[int, int], dict[int, int]]:
    """H (n, n) = A^T A of the graph linearised at `values`, each key's first column and
    tangent dimension (columns in increasing key order, as `sparseJacobian_` lays them)."""
    linear = graph.linearize(values)
    zero = values.zeroVectors()
    offset, dim, n = {}, {}, 0
    keys = values.keys()  # increasing
    for k in keys:
        offset[k], dim[k] = n, zero.dim(k)
        n += dim[k]
    rows, cols, vals = linear.sparseJacobian_()  # 1-based; column n + 1 is the right-hand side
    rows, cols = rows.astype(np.int64) - 1, cols.astype(np.int64) - 1
    inside = cols < n
    A = sp.csr_matrix((vals[inside], (rows[inside], cols[inside])), shape=(int(rows.max()) + 1, n))
    return (A.T @ A).tocsr(), offset, dim
