"""Measurement updates of the EKF and of the nonlinear H-infinity filter: the paper's section
"Nonlinear H-infinity filter", restated in DESIGN.md section 2. Everything NH-infinity is here:
the noise scaling of the paper's eq. 13-14, the corrector, the bound gamma and its policy.

Eq. 13-14 (the scaled problem): the linearisation errors are absorbed by running the filter on
the process and measurement noise scaled by c_w, c_v >= 1,

    Q_hat = c_w^2 Q   (eq. 13),    R_hat = c_v^2 R   (eq. 14)

and *only* `FilterSettings.process_noise` and `FilterSettings.measurement_noise` apply them
(the EKF uses Q and R as they are). Callers: the prediction (`slam.py`, Q of the motion
model), the innovation covariances of data association (`association.predict_in_state`) and
the update itself (`update_inplace`).

The corrector, with the predicted state x (n,), covariance P (n, n), measurement y (m,),
predicted measurement h (m,), Jacobian H (m, n) (or only its non-zero columns `cols`), R_hat
(m, m) and the bound gamma on a chosen set of states (indices `bounded`, the matrix L
selecting them; all states when None):

    K  = P H^T (H P H^T + R_hat)^-1,   x+ = x + K (y - h)
    S  = [[L P L^T - gamma^2 I, L P H^T], [H P L^T, H P H^T + R_hat]]
    P+ = P - P [L^T H^T] S^-1 [L; H] P  =  (P^-1 + H^T R_hat^-1 H - gamma^-2 L^T L)^-1

`hinf_update_block_form` is that block-Sigma form written out: the readable reference the
tests compare the fast forms against. The fast forms evaluate it through the EKF posterior
P_ekf = P - K H P = (P^-1 + H^T R_hat^-1 H)^-1 and the matrix inversion lemma (the same P+,
to rounding):

    P+ = P_ekf + P_ekf L^T (gamma^2 I - L P_ekf L^T)^-1 L P_ekf

It exists only while P_ekf^-1 - gamma^-2 L^T L is positive definite, i.e. while the largest
eigenvalue of L P_ekf L^T is below gamma^2: the matrix inverted above is then positive
definite. The gamma policy (`GammaPolicy`, the one owner of gamma): when the condition fails,
gamma is raised to sqrt((1 + margin) * lambda_max) for this update and the result says so
(the filter never produces a covariance that is not positive definite); the raised value
holds from then on (it only grows), so that a covariance that has outgrown gamma is not
inflated again at every update (which runs away). As gamma -> infinity the correction
vanishes and P+ is the EKF posterior (a test, not an assumption).

Cost: P H^T is n x m (only `cols` of P are read), the EKF posterior one n x n x m product,
the bound one n x n x l product: O(n^2 (m + l)); with L selecting the vehicle states this
is O(n^2) in the state size. With S = C C^T (Cholesky), V = P H^T C^-T gives
K = V C^-1 and P_ekf = P - V V^T.

`ekf_update` and `hinf_update` are the pure functions (they return new arrays).
`ekf_update_inplace` and `hinf_update_inplace` (used by `update_inplace`, the filter's update
as configured) evaluate the same expressions in the same order on the caller's x and P,
writing every n x n product into caller-owned work buffers: no n x n array is allocated per
update (with the bound on a few states), which keeps large freed temporaries from going back
to the OS and being faulted in again at every update (BENCHMARKS.md, "Fuse: speed"). numpy
evaluates `V @ V.T` and `G.T @ G` with syrk, whose result is exactly symmetric, so the
in-place NH-infinity update needs no symmetrisation pass; it calls syrk itself, with
beta = 1, on P's upper triangle where it lies (P - V V^T, then + G^T G; P is a view of the
state's storage, whose rows are longer than n, so BLAS is called with that leading
dimension: `_syrk_upper`) and mirrors the triangle once, instead of forming both products
apart and adding them: the same numbers, three passes over n x n fewer. Both variants give
the pure functions' results bit for bit here (the tests allow 1e-12 of the covariance's
scale). The EKF's Joseph form keeps its two n x n x m products and its symmetrisation pass
(in the two contiguous work buffers, so that the state's strided P is read and written
once): about twice the NH-infinity update's arithmetic.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy.linalg import cython_blas, solve_triangular
from scipy.linalg.blas import dtrsm

from cvslam_cli.records.arrays import F64, I64


@dataclass(frozen=True)
class FilterSettings:
    """kind: "ekf" or "hinf"; the H-infinity filter scales Q by c_w^2 and R by c_v^2 (eq.
    13-14) and puts the bound gamma on the vehicle states ("vehicle"), on the observing
    vehicle's only ("observer", `JointState.bounded_states`) or on all states ("all");
    `gamma_margin`: how far above the largest eigenvalue a raised gamma^2 goes."""

    kind: str = "hinf"
    gamma: float = 30.0
    c_w: float = 1.0
    c_v: float = 1.0
    bound: str = "vehicle"
    gamma_margin: float = 10.0

    @property
    def q_scale(self) -> float:
        return self.c_w**2 if self.kind == "hinf" else 1.0

    @property
    def r_scale(self) -> float:
        return self.c_v**2 if self.kind == "hinf" else 1.0

    def process_noise(self, Q: F64) -> F64:
        """Q_hat = c_w^2 Q (eq. 13); Q for the EKF."""
        return self.q_scale * Q

    def measurement_noise(self, R: F64) -> F64:
        """R_hat = c_v^2 R (eq. 14); R for the EKF."""
        return self.r_scale * R


class GammaPolicy:
    """The bound gamma in use over a run (module docstring): the configured value until the
    existence condition first fails, then the raised value (it only grows). `raised_count`:
    the updates in which it was raised."""

    def __init__(self, settings: FilterSettings) -> None:
        self.configured = settings.gamma
        self.margin = settings.gamma_margin
        self.raised: float | None = None
        self.raised_count = 0

    @property
    def gamma(self) -> float:
        """The gamma of the next update."""
        return self.raised if self.raised is not None else self.configured

    def record(self, result: UpdateResult) -> None:
        """Adopt a gamma the update had to raise."""
        if result.gamma_raised:
            self.raised = result.gamma
            self.raised_count += 1


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """x (n,), P (n, n) (from the in-place variants: the caller's arrays, updated, so they
    change with the state); nis: normalised innovation squared; gamma: the bound used;
    gamma_raised: the existence condition failed with the configured gamma."""

    x: F64
    P: F64
    nis: float
    gamma: float = float("inf")
    gamma_raised: bool = False


@dataclass(frozen=True)
class BlockRows:
    """What is known of a stacked H (m, len(cols)): its first `shared` columns are dense,
    the next block-diagonal with k blocks of `rows` x `width` (observation j's rows touch the
    shared columns and block j's only), and the last `tail` columns touched only by the
    rows after the k blocks' (dense among themselves). `update.py`'s H: the observing
    vehicle's columns, then each landmark's (its anchor's and its own), then the sliding
    window's rows on their clones' columns."""

    shared: int
    rows: int
    width: int
    tail: int = 0

    def HP(self, P: F64, H: F64, cols: I64) -> F64:
        """(P H^T)^T = H P[cols] (m, n) from the non-zero blocks only: the shared part
        H_v P[cols_v] (rows of the blocks x shared x n), per block H_j P[cols_j] (rows x
        width x n) and the tail's H_t P[cols_t], in place of the dense m x len(cols) x n
        product (len(cols) = shared + k width + tail). P is symmetric. Equal to the dense
        product up to rounding (the sums' terms are grouped differently)."""
        a, r, d, t = self.shared, self.rows, self.width, self.tail
        k = (len(cols) - a - t) // d
        m = k * r  # the blocks' rows; the tail's follow
        c = len(cols) - t
        HP = np.empty((len(H), P.shape[0]))
        HP[:m] = H[:m, :a] @ P[cols[:a]]
        blocks = H[:m, a:c].reshape(k, r, k, d)[np.arange(k), :, np.arange(k), :]  # (k, r, d)
        HP[:m] += (blocks @ P[cols[a:c]].reshape(k, d, -1)).reshape(m, -1)
        if len(H) > m:
            HP[m:] = H[m:, c:] @ P[cols[c:]]
        return HP

    def HPHt(self, HP: F64, H: F64, cols: I64) -> F64:
        """H P H^T (m, m) from HP = H P (m, n) (`HP`) and H's non-zero blocks only: the
        blocks' rows from HP's shared columns times H_v^T and, per block j, HP's columns
        cols_j times H_j^T (m x width x rows each); the tail's rows from its own columns.
        In place of the dense m x len(cols) x m product, equal to it up to rounding."""
        a, r, d, t = self.shared, self.rows, self.width, self.tail
        k = (len(cols) - a - t) // d
        m, c, M = k * r, len(cols) - t, len(H)
        S = np.empty((M, M))
        S[:, :m] = HP[:, cols[:a]] @ H[:m, :a].T
        blocks = H[:m, a:c].reshape(k, r, k, d)[np.arange(k), :, np.arange(k), :]  # (k, r, d)
        HP_b = HP[:, cols[a:c]].reshape(M, k, d).transpose(1, 0, 2)  # (k, M, d)
        S[:, :m] += (HP_b @ blocks.transpose(0, 2, 1)).transpose(1, 0, 2).reshape(M, m)
        if m < M:
            S[:, m:] = HP[:, cols[c:]] @ H[m:, c:].T
        return S


def _solve_lower(C: F64, B: F64) -> F64:
    """C^-1 B for C lower triangular (a Cholesky factor, finite by construction) and B (m, n)
    large: `solve_triangular` without its finiteness scan of B (a full pass, as long as the
    solve at a two-UAV state's size). A non-finite state still shows: the frame's record
    checks the vehicle's state and covariance (`Slam._record`: divergence)."""
    return solve_triangular(C, B, lower=True, check_finite=False)


def _solve_right_lower_t(C: F64, B: F64, overwrite: bool) -> F64:
    """B C^-T (n, m) for C (m, m) lower triangular (a Cholesky factor, finite by
    construction) and B (n, m): BLAS trsm from the right, column-major; with `overwrite`
    and B column-major (P H^T as `_whitened` forms it) in B itself, else in a copy.
    Solving from the left (C^-1 B^T) would copy B^T into column-major order first."""
    return dtrsm(1.0, C, B, side=1, lower=1, trans_a=1, overwrite_b=int(overwrite))


def _whitened(
    P: F64,
    H: F64,
    R: F64,
    y: F64,
    h: F64,
    cols: I64 | None,
    blocks: BlockRows | None = None,
    keep_PHt: bool = True,
) -> tuple[F64 | None, F64, F64, F64, F64, float]:
    """P H^T (n, m), S = H P H^T + R and its Cholesky factor C (lower), V = P H^T C^-T,
    w = C^-1 (y - h), NIS = |w|^2. H may touch only the state columns `cols` (then H is
    (m, len(cols)) and P H^T costs n * len(cols) * m). P is a covariance, exactly
    symmetric: with `cols`, P[:, cols] is read as P[cols].T, from P's rows (one contiguous
    copy each; P[:, cols] reads len(cols) scattered numbers from every row). `blocks`: H's
    known zeros (`BlockRows`), skipped in P H^T and in S. V is solved from the right, in
    the column-major P H^T itself (`_solve_right_lower_t`: no copy), and comes back
    column-major, as the rank-k update reads it; without `keep_PHt` that overwrites P H^T
    (None is returned for it)."""
    if cols is None:
        PHt = P @ H.T
        S = H @ PHt + R
    elif blocks is not None:
        HP = blocks.HP(P, H, cols)
        PHt = HP.T
        S = blocks.HPHt(HP, H, cols) + R
    else:
        PHt = P[cols].T @ H.T  # P[cols].T: the same (n, len(cols)) numbers as P[:, cols]
        S = H @ PHt[cols] + R
    C = np.linalg.cholesky(0.5 * (S + S.T))
    V = _solve_right_lower_t(C, PHt, overwrite=not keep_PHt)  # (n, m)
    w = solve_triangular(C, y - h, lower=True)
    return (PHt if keep_PHt else None), S, C, V, w, float(w @ w)


def ekf_update(
    x: F64, P: F64, y: F64, h: F64, H: F64, R: F64, cols: I64 | None = None
) -> UpdateResult:
    """EKF update in Joseph form P+ = (I - K H) P (I - K H)^T + K R K^T, evaluated without
    forming I - K H: P+ = P - K (P H^T)^T - (P H^T) K^T + K S K^T, O(n^2 m).
    `cols`: the state columns H touches (H is (m, len(cols))); None: H is (m, n)."""
    PHt, S, C, V, w, nis = _whitened(P, H, R, y, h, cols)
    K = solve_triangular(C, V.T, lower=True, trans="T").T  # V C^-1 = P H^T S^-1
    D = S @ K.T - PHt.T  # (m, n), zero in exact arithmetic: K S K^T - K PHt^T = K D
    P_new = P + K @ D - PHt @ K.T
    return UpdateResult(x + V @ w, 0.5 * (P_new + P_new.T), nis)


def _existence_check(P_ekf_LL: F64, gamma: float, margin: float) -> tuple[float, bool]:
    """(gamma to use, whether it was raised): the bound exists while the largest eigenvalue
    of L P_ekf L^T (l, l) is below gamma^2 / (1 + margin); else gamma^2 is raised to
    (1 + margin) lambda_max (module docstring, the gamma policy)."""
    lam = float(np.linalg.eigvalsh(P_ekf_LL)[-1])
    if np.isfinite(gamma) and lam >= gamma**2 / (1.0 + margin):
        return float(np.sqrt((1.0 + margin) * lam)), True
    return gamma, False


def hinf_update(
    x: F64,
    P: F64,
    y: F64,
    h: F64,
    H: F64,
    R_hat: F64,
    gamma: float,
    bounded: I64 | None = None,
    margin: float = 0.1,
    cols: I64 | None = None,
) -> UpdateResult:
    """Nonlinear H-infinity update (module docstring); `bounded`: indices of the states the
    bound is put on (None: all); `cols`: the state columns H touches (as in `ekf_update`)."""
    n = len(x)
    idx = np.arange(n) if bounded is None else np.asarray(bounded, dtype=np.int64)
    _, _, _, V, w, nis = _whitened(P, H, R_hat, y, h, cols)
    P_ekf = P - V @ V.T
    P_ekf_L = P_ekf[:, idx]  # P_ekf L^T, (n, l)
    P_ekf_LL = 0.5 * (P_ekf_L[idx] + P_ekf_L[idx].T)
    gamma, raised = _existence_check(P_ekf_LL, gamma, margin)
    x_new = x + V @ w
    if not np.isfinite(gamma):
        return UpdateResult(x_new, 0.5 * (P_ekf + P_ekf.T), nis, gamma, False)
    B = np.linalg.cholesky(gamma**2 * np.eye(len(idx)) - P_ekf_LL)  # exists: lam < gamma^2
    G = _solve_lower(B, P_ekf_L.T)  # (l, n)
    P_new = P_ekf + G.T @ G
    return UpdateResult(x_new, 0.5 * (P_new + P_new.T), nis, gamma, raised)


def hinf_update_block_form(
    x: F64, P: F64, y: F64, h: F64, H: F64, R_hat: F64, gamma: float, bounded: I64 | None = None
) -> UpdateResult:
    """The paper's corrector written out with its block matrix Sigma (module docstring), H
    (m, n) dense: the reference the fast forms are tested against. O(n^3); no existence
    check (gamma must satisfy it)."""
    n = len(x)
    L = np.eye(n) if bounded is None else np.eye(n)[np.asarray(bounded, dtype=np.int64)]
    S = H @ P @ H.T + R_hat
    K = P @ H.T @ np.linalg.inv(S)
    W = np.concatenate([P @ L.T, P @ H.T], axis=1)  # P [L^T H^T]
    Sigma = np.block([[L @ P @ L.T - gamma**2 * np.eye(len(L)), L @ P @ H.T],
                      [H @ P @ L.T, S]])  # fmt: skip
    nu = y - h
    return UpdateResult(
        x + K @ nu, P - W @ np.linalg.solve(Sigma, W.T), float(nu @ np.linalg.solve(S, nu)), gamma
    )


def _check_inplace(x: F64, P: F64, work: F64) -> None:
    n = len(x)
    if P.shape != (n, n) or work.shape != (2, n, n):
        raise ValueError(
            f"in-place update: expected P of shape ({n}, {n}) and work of shape (2, {n}, {n}) "
            f"for x of length {n}, got {P.shape} and {work.shape}"
        )
    if np.may_share_memory(P, work) or np.may_share_memory(x, work):
        raise ValueError("in-place update: the work buffer must not overlap x or P")


def ekf_update_inplace(
    x: F64,
    P: F64,
    y: F64,
    h: F64,
    H: F64,
    R: F64,
    cols: I64 | None,
    work: F64,
    blocks: BlockRows | None = None,
) -> UpdateResult:
    """`ekf_update` (Joseph form, same expressions in the same order) written into x (n,)
    and P (n, n) in place; `work` (2, n, n) is scratch space (two C-contiguous (n, n)
    buffers) that must not overlap them; `blocks`: H's known zeros (`BlockRows`). The
    result holds x and P themselves."""
    _check_inplace(x, P, work)
    w1, w2 = work[0], work[1]
    PHt, S, C, V, w, nis = _whitened(P, H, R, y, h, cols, blocks)
    K = solve_triangular(C, V.T, lower=True, trans="T").T  # V C^-1 = P H^T S^-1
    D = S @ K.T - PHt.T  # (m, n)
    # P+ = P + K D - (P H^T) K^T, then 0.5 (P+ + P+^T): two n x n x m products
    np.matmul(K, D, out=w1)
    np.add(P, w1, out=w1)
    np.matmul(PHt, K.T, out=w2)
    np.subtract(w1, w2, out=w1)
    np.add(w1, w1.T, out=w2)
    np.multiply(w2, 0.5, out=P)
    x += V @ w
    return UpdateResult(x, P, nis)


def hinf_update_inplace(
    x: F64,
    P: F64,
    y: F64,
    h: F64,
    H: F64,
    R_hat: F64,
    gamma: float,
    bounded: I64 | None,
    margin: float,
    cols: I64 | None,
    work: F64,
    blocks: BlockRows | None = None,
) -> UpdateResult:
    """`hinf_update` written into x (n,) and P (n, n) in place; `work` (2, n, n) is scratch
    space (two C-contiguous (n, n) buffers) that must not overlap them; `blocks`: H's known
    zeros (`BlockRows`). Same expressions in the same order as `hinf_update`, evaluated as
    two symmetric rank updates of P's upper triangle where it lies (BLAS syrk with beta = 1:
    P_ekf = P - V V^T, the existence check on the bounded rows of P_ekf, then P_ekf + G^T G;
    work[1] holds all of P_ekf when every state is bounded), mirrored into P's lower triangle
    at the end: one pass over P, where a copy of P and forming V V^T and G^T G apart would
    cost three more. The numbers are those of numpy's V @ V.T (syrk as well) and of the
    subtraction and addition, bit for bit; P stays exactly symmetric. The result holds x and
    P themselves."""
    _check_inplace(x, P, work)
    _, _, _, V, w, nis = _whitened(P, H, R_hat, y, h, cols, blocks, keep_PHt=False)
    _syrk_upper(P, V, -1.0)  # P's upper triangle: P_ekf = P - V V^T
    if bounded is None:  # every state bounded: L = I, P_ekf L^T is all of P_ekf
        P_ekf_L = work[1]
        np.copyto(P_ekf_L, P)
        _mirror_upper(P_ekf_L)
        P_ekf_LL = P_ekf_L
    else:
        idx = np.asarray(bounded, dtype=np.int64)
        P_ekf_L = _upper_rows(P, idx).T  # P_ekf L^T (n, l)
        P_ekf_LL = P_ekf_L[idx]
    P_ekf_LL = 0.5 * (P_ekf_LL + P_ekf_LL.T)
    gamma, raised = _existence_check(P_ekf_LL, gamma, margin)
    x += V @ w
    if np.isfinite(gamma):
        B = np.linalg.cholesky(gamma**2 * np.eye(len(P_ekf_LL)) - P_ekf_LL)
        G = _solve_lower(B, P_ekf_L.T)  # (l, n)
        _syrk_upper(P, G.T, 1.0)  # P_ekf + G^T G
    _mirror_upper(P)
    return UpdateResult(x, P, nis, gamma, raised)


@cache
def _dsyrk() -> Callable[..., None]:
    """BLAS dsyrk as scipy exports it for Cython (`scipy.linalg.cython_blas`, the library
    `scipy.linalg.blas` wraps), called through ctypes: the f2py wrapper accepts only a
    contiguous C, and P is a view of the state's larger storage."""
    api = ctypes.pythonapi
    api.PyCapsule_GetName.restype = ctypes.c_char_p
    api.PyCapsule_GetName.argtypes = [ctypes.py_object]
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    capsule = cython_blas.__pyx_capi__["dsyrk"]
    pointer = api.PyCapsule_GetPointer(capsule, api.PyCapsule_GetName(capsule))
    i, d, a = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_double), ctypes.c_void_p
    c = ctypes.c_char_p
    return ctypes.CFUNCTYPE(None, c, c, i, i, d, a, i, d, a, i)(pointer)  # uplo .. ldc


def _syrk_upper(P: F64, A: F64, alpha: float) -> None:
    """P's upper triangle += alpha A A^T (A (n, k)), in place: BLAS dsyrk on the lower
    triangle of P^T, the column-major matrix whose leading dimension is P's row stride (P
    (n, n) with contiguous rows; its lower triangle is left as it was)."""
    n, k = A.shape
    if P.shape != (n, n) or P.strides[1] != P.itemsize or P.dtype != np.float64:
        raise ValueError(f"syrk: expected an (n, n) float64 view with contiguous rows, n = {n}")
    A = np.asfortranarray(A, dtype=np.float64)
    ref = ctypes.byref
    _dsyrk()(
        b"L", b"N", ref(ctypes.c_int(n)), ref(ctypes.c_int(k)), ref(ctypes.c_double(alpha)),
        A.ctypes.data, ref(ctypes.c_int(max(n, 1))), ref(ctypes.c_double(1.0)), P.ctypes.data,
        ref(ctypes.c_int(max(P.strides[0] // P.itemsize, 1))),
    )  # fmt: skip


def _upper_rows(acc: F64, rows: I64) -> F64:
    """(l, n) full rows of the symmetric matrix whose upper triangle acc holds: row i is
    acc[:i, i] (read down the column) then acc[i, i:]."""
    out = np.empty((len(rows), len(acc)))
    for r, i in enumerate(rows):
        out[r, :i] = acc[:i, i]
        out[r, i:] = acc[i, i:]
    return out


_MIRROR_BLOCK = 64
_STRICT_LOWER = np.tril(np.ones((_MIRROR_BLOCK, _MIRROR_BLOCK), dtype=bool), -1)


def _mirror_upper(P: F64) -> None:
    """P (n, n) made the symmetric matrix whose upper triangle it holds, in place, by blocks
    of 64 rows (measured fastest of 64 / 128 / 256 at n = 544 and 914): the transpose of the
    block's part right of its diagonal block below it, and the diagonal block's strict lower
    part from its upper."""
    n = len(P)
    for j0 in range(0, n, _MIRROR_BLOCK):
        j1 = min(n, j0 + _MIRROR_BLOCK)
        P[j1:, j0:j1] = P[j0:j1, j1:].T
        D = P[j0:j1, j0:j1]
        b = j1 - j0
        np.copyto(D, D.T.copy(), where=_STRICT_LOWER[:b, :b])


def update_inplace(
    settings: FilterSettings,
    policy: GammaPolicy,
    x: F64,
    P: F64,
    y: F64,
    h: F64,
    H: F64,
    cols: I64 | None,
    R: F64,
    bounded: I64 | None,
    work: F64,
    blocks: BlockRows | None = None,
) -> UpdateResult:
    """The filter's measurement update as configured, in place on x (n,) and P (n, n)
    (`work` (2, n, n) scratch): the EKF with R, or NH-infinity with R_hat = c_v^2 R (eq. 14),
    the policy's gamma on the states `bounded` (None: all). NH-infinity bounding no state
    is the EKF with R_hat. `blocks`: H's known zeros (`BlockRows`)."""
    R_hat = settings.measurement_noise(R)
    if settings.kind == "ekf" or (bounded is not None and len(bounded) == 0):
        return ekf_update_inplace(x, P, y, h, H, R_hat, cols, work, blocks)
    res = hinf_update_inplace(
        x, P, y, h, H, R_hat, policy.gamma, bounded, policy.margin, cols, work, blocks
    )
    policy.record(res)
    return res
