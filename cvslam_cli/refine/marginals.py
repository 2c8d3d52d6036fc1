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

Landmarks' marginals without a solve of their own (`poses_and_landmarks`): a landmark l is
tied by its reprojection factors to keyframe poses only, so with H_ll its own 3 x 3 block,
H_lP its block against the pose columns P and Sigma_PP the poses' joint marginal (the
partitioned inverse, the Schur complement that eliminates l),

    Sigma_ll = H_ll^-1 + G_l Sigma_PP G_l^T,   G_l = H_ll^-1 H_lP,

exact, and Sigma_PP comes column batch by column batch from the same solves that give the
poses' own marginals: every landmark costs a few sparse products instead of 3 solves (the
`uav2_paper` mission's 14 000 points would take ~6 times the poses' solves,
BENCHMARKS.md "Refine (issue 21)").
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
    information: sp.csr_matrix

    def _columns(self, keys: Sequence[int], d: int) -> np.ndarray:
        first = np.array([self.offset[k] for k in keys], dtype=np.int64)
        return (first[:, None] + np.arange(d)).ravel()

    def _solve(self, cols: np.ndarray) -> F64:
        """(n, len(cols)) columns `cols` of Sigma = H^-1."""
        rhs = np.zeros((len(self.scale), len(cols)))
        rhs[cols, np.arange(len(cols))] = 1.0
        return self.lu.solve(rhs) * np.outer(self.scale, self.scale[cols])

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
        out, _ = self.poses_and_landmarks(keys, [], progress, dims.pop())
        return out

    def poses_and_landmarks(
        self,
        keys: Sequence[int],
        landmark_keys: Sequence[int],
        progress: Callable[[int], None] | None = None,
        d: int = 6,
    ) -> tuple[F64, F64]:
        """((len(keys), d, d), (len(landmark_keys), 3, 3)): the marginal covariances of
        `keys` (all of tangent dimension d), from their columns of Sigma, and of the 3-D
        `landmark_keys`, whose factors may tie them to `keys` only, by the Schur complement
        (module docstring); `progress(k)`: k more of `keys` done."""
        columns = self._columns(keys, d)
        n_l = len(landmark_keys)
        lm = _LandmarkBlocks(self, landmark_keys, columns) if n_l else None
        out = np.empty((len(keys), d, d))
        lm_out = np.zeros((n_l, 3, 3))
        per_batch = max(1, BATCH_COLUMNS // d)
        for i in range(0, len(keys), per_batch):
            at = np.arange(i * d, min((i + per_batch) * d, len(columns)))
            sigma = self._solve(columns[at])
            block = sigma[columns[at]]
            m = len(at) // d
            blocks = block.reshape(m, d, m, d)[np.arange(m), :, np.arange(m), :]
            out[i : i + m] = 0.5 * (blocks + blocks.transpose(0, 2, 1))
            if lm is not None:
                lm_out += lm.term(sigma[columns], at)
            if progress is not None:
                progress(m)
        if lm is not None:
            lm_out += lm.A_inv
            lm_out = 0.5 * (lm_out + lm_out.transpose(0, 2, 1))
        return out, lm_out


class _LandmarkBlocks:
    """The landmarks' parts of H for `Factorisation.poses_and_landmarks`: A_inv (L, 3, 3) =
    H_ll^-1 and G (3L, |P|) = blockdiag(H_ll^-1) H_lP over the pose columns P."""

    def __init__(self, f: Factorisation, keys: Sequence[int], pose_columns: np.ndarray) -> None:
        H = f.information
        rows = f._columns(keys, 3)
        n_l = len(keys)
        H_l = H[rows]
        ii = np.repeat(np.arange(3 * n_l).reshape(n_l, 3), 3, axis=1).ravel()
        jj = np.tile(rows.reshape(n_l, 3), (1, 3)).ravel()
        A = np.asarray(H_l[ii, jj]).reshape(n_l, 3, 3)
        self.A_inv = np.linalg.inv(A)
        position = np.full(H.shape[1], -1, dtype=np.int64)
        position[pose_columns] = np.arange(len(pose_columns))
        coo = H_l.tocoo()
        landmark_of = np.full(H.shape[1], -1, dtype=np.int64)
        landmark_of[rows] = np.arange(3 * n_l) // 3
        own = landmark_of[coo.col] == coo.row // 3
        where = position[coo.col[~own]]
        if np.any(where < 0):
            raise ValueError("a landmark is tied to a variable other than the poses")
        # (another landmark's columns are not in P: a factor between landmarks is refused)
        H_lP = sp.csr_matrix(
            (coo.data[~own], (coo.row[~own], where)), shape=(3 * n_l, len(pose_columns))
        )
        blocks = sp.bsr_matrix(
            (self.A_inv, np.arange(n_l), np.arange(n_l + 1)), shape=(3 * n_l, 3 * n_l)
        )
        self.G = (blocks @ H_lP).tocsr()

    def term(self, sigma_P: F64, at: np.ndarray) -> F64:
        """(L, 3, 3): the part of G_l Sigma_PP G_l^T from the pose columns `at` (indices
        into P), given Sigma's rows P at those columns, sigma_P (|P|, len(at))."""
        M = self.G @ sigma_P  # (3L, len(at))
        G_at = self.G[:, at]
        out = np.empty((self.G.shape[0] // 3, 3, 3))
        for i in range(3):
            for j in range(3):
                out[:, i, j] = np.asarray(G_at[j::3].multiply(M[i::3]).sum(axis=1)).ravel()
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
    return Factorisation(lu, scale, offset, dim, H)


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
