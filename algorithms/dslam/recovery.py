"""State recovery for D-SLAM: x = I^-1 i and covariance columns, without ever inverting I.

Section 3.2-3.3 of [1]_: the map update (eq. 10) needs the current estimate of the observed
features, localization and data association need the estimates and the covariance of the
features near the robot. Both come from sparse linear solves with I:

- the estimate solves ``I x = i`` (eq. 6), warm-started from the previous estimate, which is
  always a good initial guess because one update changes I and i on a few features only;
- covariance column j solves ``I c = e_j``, so the joint covariance of k features costs 2k
  solves, never an inverse.

Solvers: preconditioned conjugate gradients with a 2x2 block-Jacobi preconditioner (several
right-hand sides in lock-step, one sparse product per iteration), a local block solve on the
neighbourhood of the updated features, and a direct sparse LU (SuperLU) as the fallback.
Convergence is measured by the block-Jacobi error estimate ``max_f |I_ff^-1 r_f|``, in metres
for the state (m^2 for covariance columns): the size of the correction each feature still needs.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, sections 3.2-3.3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from algorithms.dslam.information import InformationMatrix, dofs

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
LOCAL_MAX_FEATURES = 64  # largest local solve (a dense 128 x 128 Cholesky)


def invert_blocks(blocks: F64) -> F64:
    """Inverses of 2x2 blocks (n, 2, 2) in closed form (singular blocks give 0: no preconditioning)."""
    a, b, c, d = blocks[:, 0, 0], blocks[:, 0, 1], blocks[:, 1, 0], blocks[:, 1, 1]
    det = a * d - b * c
    ok = np.abs(det) > 1e-300
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    return np.stack([np.stack([d, -b], -1), np.stack([-c, a], -1)], -2) * inv_det[:, None, None]


def apply_blocks(inv_blocks: F64, r: F64) -> F64:
    """Block-diagonal product D^-1 r for r (2n,) or (2n, k)."""
    n = len(inv_blocks)
    if r.ndim == 1:
        return np.einsum("nij,nj->ni", inv_blocks, r.reshape(n, 2)).reshape(-1)
    return np.einsum("nij,njk->nik", inv_blocks, r.reshape(n, 2, -1)).reshape(r.shape)


def error_estimate(inv_blocks: F64, r: F64) -> F64:
    """Block-Jacobi error estimate per column: max over features of |D_f^-1 r_f| (scalar or (k,))."""
    e = apply_blocks(inv_blocks, r)
    return np.max(np.abs(e), axis=0) if len(e) else np.zeros(e.shape[1:])


@dataclass(frozen=True, slots=True)
class SolveResult:
    """Solution (2N,) or (2N, k), the iterations used and whether every column met its tolerance."""

    x: F64
    iterations: int
    converged: bool


def pcg(info: InformationMatrix, b: F64, x0: F64, inv_blocks: F64, tol: float | F64,
        maxiter: int) -> SolveResult:
    """Block-Jacobi preconditioned CG on ``I x = b`` from ``x0``; columns of b iterate in lock-step.

    A column stops when its error estimate (module docstring) is at most ``tol`` (scalar or (k,)).
    """
    single = b.ndim == 1
    B = b[:, None] if single else b
    X = (x0[:, None] if single else x0).copy()
    tol_arr = np.broadcast_to(np.asarray(tol, dtype=np.float64), (B.shape[1],))
    R = B - info.matvec(X)
    Z = apply_blocks(inv_blocks, R)
    active = np.max(np.abs(Z), axis=0) > tol_arr if len(Z) else np.zeros(B.shape[1], bool)
    P = Z.copy()
    rz = np.einsum("ij,ij->j", R, Z)
    it = 0
    while active.any() and it < maxiter:
        it += 1
        cols = np.flatnonzero(active)
        Ap = info.matvec(P[:, cols])
        pap = np.einsum("ij,ij->j", P[:, cols], Ap)
        alpha = np.where(pap > 0, rz[cols] / np.where(pap > 0, pap, 1.0), 0.0)
        X[:, cols] += P[:, cols] * alpha
        R[:, cols] -= Ap * alpha
        Zc = apply_blocks(inv_blocks, R[:, cols])
        rz_new = np.einsum("ij,ij->j", R[:, cols], Zc)
        beta = np.where(rz[cols] > 0, rz_new / np.where(rz[cols] > 0, rz[cols], 1.0), 0.0)
        P[:, cols] = Zc + P[:, cols] * beta
        rz[cols] = rz_new
        done = (np.max(np.abs(Zc), axis=0) <= tol_arr[cols]) | (pap <= 0)
        active[cols[done]] = False
    x = X[:, 0] if single else X
    return SolveResult(x=x, iterations=it, converged=not active.any())


def factor(info: InformationMatrix) -> spla.SuperLU:
    """Sparse LU factors of I (SuperLU, minimum-degree ordering of I + I^T)."""
    return spla.splu(info.csc(), permc_spec="MMD_AT_PLUS_A")


def direct(info: InformationMatrix, b: F64) -> F64:
    """Direct sparse solve of ``I x = b`` (b (2N,) or (2N, k))."""
    if info.n == 0:
        return np.zeros_like(b)
    return np.asarray(factor(info).solve(b))


def neighbourhood(info: InformationMatrix, features: list[int], hops: int) -> list[int]:
    """``features`` and every feature within ``hops`` links of them, sorted."""
    region = set(features)
    frontier = set(features)
    for _ in range(hops):
        nxt: set[int] = set()
        for f in frontier:
            nxt |= info.neighbours[f]
        frontier = nxt - region
        region |= frontier
        if not frontier:
            break
    return sorted(region)


def local_solve(info: InformationMatrix, x: F64, r: F64, region: list[int]) -> None:
    """Solve ``I_OO d = r_O`` on the features ``region`` (O), then ``x_O += d`` and ``r -= I[:, O] d``.

    ``x`` and ``r`` are updated in place. Exact on O; the residual moves to O's neighbours.
    """
    idx = dofs(region)
    rows, cols, vals = info.row_entries(idx)
    local = np.full(len(x), -1, dtype=np.int64)
    local[idx] = np.arange(len(idx))
    inside = local[cols] >= 0
    block = np.zeros((len(idx), len(idx)))
    np.add.at(block, (rows[inside], local[cols[inside]]), vals[inside])
    delta = sla.cho_solve(sla.cho_factor(0.5 * (block + block.T)), r[idx])
    x[idx] += delta
    np.add.at(r, cols, -vals * delta[rows])  # I is symmetric: column O of I is row O transposed


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """How one recovery went: the method, PCG iterations, features in the local solve, final error estimate (m)."""

    method: str  # "local", "pcg", "direct" or "none"
    iterations: int
    region: int
    error_m: float


class Recovery:
    """The recovered state ``x`` (2N,) of an information matrix, kept with its residual ``r = i - I x``.

    Modes: ``"pcg"`` solves the whole system by warm-started PCG after every update, falling back
    to a direct solve when PCG does not converge and after a loop closure ([1]_ section 3.3);
    ``"local"`` first solves exactly on the updated features and their neighbours (up to
    ``max_hops`` links away and LOCAL_MAX_FEATURES features) and accepts the result when the
    error estimate of the whole state is at most ``local_tol_m``, with a global PCG every
    ``global_every`` updates and whenever the local solve is not enough (a direct solve after a
    loop closure); ``"direct"`` always solves directly (reference).
    """

    def __init__(self, info: InformationMatrix, mode: str, tol_m: float, local_tol_m: float, max_hops: int,
                 maxiter: int, global_every: int) -> None:
        self.info = info
        self.mode, self.tol_m, self.local_tol_m = mode, tol_m, local_tol_m
        self.max_hops, self.maxiter, self.global_every = max_hops, maxiter, global_every
        self.x = np.zeros(0)
        self.r = np.zeros(0)
        self.inv_blocks = np.zeros((0, 2, 2))
        self._since_global = 0

    def grow(self, positions: F64) -> None:
        """Append features (k, 2) at these initial estimates (their residual is 0: I and i are 0 there)."""
        self.x = np.concatenate([self.x, positions.reshape(-1)])
        self.r = np.concatenate([self.r, np.zeros(positions.size)])
        self.inv_blocks = np.concatenate([self.inv_blocks, np.zeros((len(positions), 2, 2))])

    def record(self, features: I64, d_matrix: F64, d_vector: F64) -> None:
        """Account for ``info.add(features, d_matrix, d_vector)``, which must already have been applied."""
        idx = dofs(features)
        self.r[idx] += d_vector - d_matrix @ self.x[idx]
        self.inv_blocks[features] = invert_blocks(self.info.diagonal_blocks(features))

    def error(self) -> float:
        """Block-Jacobi estimate of the largest remaining correction of any feature (m)."""
        return float(error_estimate(self.inv_blocks, self.r)) if len(self.r) else 0.0

    def _set(self, x: F64) -> None:
        self.x = x
        self.r = self.info.vector - self.info.matvec(x)
        self._since_global = 0

    def solve_direct(self) -> RecoveryReport:
        """x = I^-1 i by sparse LU."""
        self._set(direct(self.info, np.array(self.info.vector)))
        return RecoveryReport("direct", 0, 0, self.error())

    def _solve_pcg(self) -> RecoveryReport:
        result = pcg(self.info, np.array(self.info.vector), self.x, self.inv_blocks, self.tol_m, self.maxiter)
        if not result.converged:
            self.solve_direct()
            return RecoveryReport("direct", result.iterations, 0, self.error())
        self._set(result.x)
        return RecoveryReport("pcg", result.iterations, 0, self.error())

    def solve(self, touched: list[int], loop_closure: bool) -> RecoveryReport:
        """Recover x after an update of the features ``touched`` (class docstring for the modes)."""
        self._since_global += 1
        if self.mode == "direct" or (loop_closure and self.mode == "pcg"):
            return self.solve_direct()
        if self.mode == "pcg" or self._since_global >= self.global_every:
            return self._solve_pcg()
        region: list[int] = []
        for hops in range(1, self.max_hops + 1):
            grown = neighbourhood(self.info, touched, hops)
            if len(grown) == len(region) or len(grown) > LOCAL_MAX_FEATURES:
                break  # nothing new, or a region too large for a dense solve: PCG instead
            region = grown
            local_solve(self.info, self.x, self.r, region)
            err = self.error()
            if err <= self.local_tol_m:
                return RecoveryReport("local", 0, len(region), err)
        return self.solve_direct() if loop_closure else self._solve_pcg()
