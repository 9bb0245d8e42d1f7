"""State recovery for D-SLAM: x = I^-1 i and covariance columns, without ever inverting I.

Section 3.2-3.3 of [1]_: the map update (eq. 10) needs the current estimate of the observed
features, localization and data association need the estimates and the covariance of the
features near the robot. Both come from sparse linear solves with I:

- the estimate solves ``I x = i`` (eq. 6), warm-started from the previous estimate, which is
  always a good initial guess because one update changes I and i on a few features only;
- covariance column j solves ``I c = e_j``, so the joint covariance of k features costs 2k
  solves, never an inverse (:mod:`slamreplay.algorithms.dslam.covariance`, for a full recomputation).

Solvers: preconditioned conjugate gradients (several right-hand sides in lock-step, one sparse
product per iteration) with a 2x2 block-Jacobi preconditioner or a two-level one
(:class:`TwoLevel`: block-Jacobi plus the rigid motions of square cells of features), a local
block solve on the neighbourhood of the updated features, and a direct sparse LU (SuperLU) as
the fallback.
Convergence is measured by the block-Jacobi error estimate ``max_f |I_ff^-1 r_f|``, in metres
for the state (m^2 for covariance columns): the size of the correction each feature still needs.

The local recovery keeps the residual ``r = i - I x`` and each feature's error estimate up to
date incrementally, with the set of features whose estimate exceeds the tolerance; an update
(eq. 10) changes r on its own features only, and a local solve on a region O changes it on O
and on O's neighbours only. Deciding that the whole state is within tolerance is then O(1):
the set is empty. Nothing in a local recovery touches all N features.

References
----------
.. [1] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation
   of D-SLAM", FSR 2005, sections 3.2-3.3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from slamreplay.algorithms.dslam.information import InformationMatrix, _grown, dofs

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
LOCAL_MAX_FEATURES = 160  # largest local solve (a dense 320 x 320 Cholesky)
COARSE_CELL_M = 10.0  # side of the square cells whose rigid motions span the coarse space


def invert_blocks(blocks: F64) -> F64:
    """Inverses of 2x2 blocks (n, 2, 2) in closed form (singular blocks give 0: no preconditioning)."""
    a, b, c, d = blocks[:, 0, 0], blocks[:, 0, 1], blocks[:, 1, 0], blocks[:, 1, 1]
    det = a * d - b * c
    ok = np.abs(det) > 1e-300
    inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    out = np.empty(blocks.shape)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = d * inv_det, -b * inv_det, -c * inv_det, a * inv_det
    return out


def apply_blocks(inv_blocks: F64, r: F64) -> F64:
    """Block-diagonal product D^-1 r for r (2n,) or (2n, k)."""
    n = len(inv_blocks)
    if r.ndim == 1:
        return cast(F64, np.einsum("nij,nj->ni", inv_blocks, r.reshape(n, 2)).reshape(-1))
    return cast(F64, np.einsum("nij,njk->nik", inv_blocks, r.reshape(n, 2, -1)).reshape(r.shape))


def block_errors(inv_blocks: F64, r: F64) -> F64:
    """Per feature, the block-Jacobi error estimate ``max |I_ff^-1 r_f|`` (n,) of r (2n,)."""
    return np.max(np.abs(apply_blocks(inv_blocks, r).reshape(-1, 2)), axis=1) if len(r) else np.zeros(0)


def error_estimate(inv_blocks: F64, r: F64) -> F64:
    """Block-Jacobi error estimate per column: max over features of |D_f^-1 r_f| (scalar or (k,))."""
    e = apply_blocks(inv_blocks, r)
    return np.max(np.abs(e), axis=0) if len(e) else np.zeros(e.shape[1:])


class Operator(Protocol):
    """A symmetric positive definite matrix known by its product (an :class:`InformationMatrix`, or SLSJF's)."""

    def matvec(self, x: F64) -> F64: ...


@dataclass(frozen=True, slots=True)
class SolveResult:
    """Solution (2N,) or (2N, k), the iterations used and whether every column met its tolerance."""

    x: F64
    iterations: int
    converged: bool


def pcg(info: Operator, b: F64, x0: F64, inv_blocks: F64 | None, tol: float | F64,
        maxiter: int, precondition: Callable[[F64], F64] | None = None) -> SolveResult:
    """Preconditioned CG on ``I x = b`` from ``x0``; columns of b iterate in lock-step.

    The preconditioner is block-Jacobi (``inv_blocks``, 2x2 blocks) unless ``precondition`` (R (n, k) ->
    M^-1 R) is given. A column stops when its preconditioned residual, the error estimate of
    the module docstring, is at most ``tol`` (scalar or (k,)) for every entry.
    """
    single = b.ndim == 1
    B = b[:, None] if single else b
    X = (x0[:, None] if single else x0).copy()
    tol_arr = np.broadcast_to(np.asarray(tol, dtype=np.float64), (B.shape[1],))

    if precondition is None and inv_blocks is None:
        raise ValueError("pcg needs inv_blocks or precondition")

    def apply(r: F64) -> F64:
        return apply_blocks(cast(F64, inv_blocks), r) if precondition is None else precondition(r)

    R = B - info.matvec(X)
    Z = apply(R)
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
        Zc = apply(R[:, cols])
        rz_new = np.einsum("ij,ij->j", R[:, cols], Zc)
        beta = np.where(rz[cols] > 0, rz_new / np.where(rz[cols] > 0, rz[cols], 1.0), 0.0)
        P[:, cols] = Zc + P[:, cols] * beta
        rz[cols] = rz_new
        done = (np.max(np.abs(Zc), axis=0) <= tol_arr[cols]) | (pap <= 0)
        active[cols[done]] = False
    x = X[:, 0] if single else X
    return SolveResult(x=x, iterations=it, converged=not active.any())


def coarse_space(x: F64, cell_m: float, poses: I64 | None = None, features: I64 | None = None) -> sp.csr_matrix:
    """The prolongation P (n, 3C): translations and a rotation of the variables of each square cell.

    Features (2 dofs at each offset in ``features``; default: all of ``x`` (n,), D-SLAM's state) and poses
    (x, y, heading at each offset in ``poses``: SLSJF's state) are grouped by the cell of side ``cell_m``
    holding their position in ``x``; each group moves rigidly in the plane (x, y and a rotation about its
    centroid, lever arms scaled by ``1 / cell_m``, which turns a pose's heading by the same angle). A group of
    one feature has no rotation column.
    """
    poses = np.zeros(0, np.int64) if poses is None else np.asarray(poses, np.int64)
    features = np.arange(0, len(x), 2, dtype=np.int64) if features is None else np.asarray(features, np.int64)
    offsets = np.concatenate([poses, features])
    is_pose = np.arange(len(offsets)) < len(poses)
    n, v = len(x), len(offsets)
    pts = np.stack([x[offsets], x[offsets + 1]], -1) if v else np.zeros((0, 2))
    _, agg = np.unique(np.floor(pts / cell_m).astype(np.int64), axis=0, return_inverse=True)
    agg = agg.reshape(-1)
    c = int(agg.max()) + 1 if v else 0
    counts = np.bincount(agg, minlength=c)
    sums = np.stack([np.bincount(agg, pts[:, 0], c), np.bincount(agg, pts[:, 1], c)], -1)
    cent = sums / np.maximum(counts, 1)[:, None]
    lever = (pts - cent[agg]) / cell_m
    rotates = (counts >= 2) | (np.bincount(agg, is_pose.astype(np.float64), c) > 0)
    rot = np.cumsum(rotates) - 1  # rotation column of each group that has one
    r = rotates[agg]
    turned = is_pose & r  # poses whose heading the rotation turns
    rows = np.concatenate([offsets, offsets + 1, offsets[r], offsets[r] + 1, offsets[turned] + 2])
    cols = np.concatenate([2 * agg, 2 * agg + 1, 2 * c + rot[agg[r]], 2 * c + rot[agg[r]], 2 * c + rot[agg[turned]]])
    vals = np.concatenate([np.ones(2 * v), -lever[r, 1], lever[r, 0], np.full(int(turned.sum()), 1.0 / cell_m)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, 2 * c + int(np.sum(rotates))))


class Coarse:
    """The coarse half of a two-level preconditioner: ``r -> P (P^T A P)^-1 P^T r`` for a prolongation P."""

    def __init__(self, a: sp.csr_matrix, p: sp.csr_matrix) -> None:
        self.p = p
        self.pt = p.T.tocsr()
        coarse = (self.pt @ (a @ p)).tocsc()
        self.lu = spla.splu(0.5 * (coarse + coarse.T), permc_spec="MMD_AT_PLUS_A") if coarse.shape[0] else None

    def __call__(self, r: F64) -> F64:
        if self.lu is None:
            return np.zeros_like(r)
        return cast(F64, self.p @ np.asarray(self.lu.solve(np.asarray(self.pt @ r))))

    @property
    def nbytes(self) -> int:
        mats = [self.p, self.pt] + ([self.lu.L, self.lu.U] if self.lu is not None else [])
        return int(sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes for m in mats))


class TwoLevel:
    """The additive two-level preconditioner ``M^-1 = D^-1 + P (P^T I P)^-1 P^T`` (D: the 2x2 diagonal blocks).

    Block-Jacobi alone leaves the smooth, map-wide part of the error (rigid motions of whole
    neighbourhoods) to hundreds of iterations; the coarse space of :func:`coarse_space` holds
    exactly those motions, so PCG converges in a few tens of iterations whatever N. Memory:
    P has 3 entries per dof, and the coarse matrix is about N / 10 dofs.
    """

    def __init__(self, info: InformationMatrix, inv_blocks: F64, x: F64, cell_m: float = COARSE_CELL_M) -> None:
        self.inv_blocks = inv_blocks
        self.coarse = Coarse(info.csr(), coarse_space(x, cell_m))

    def __call__(self, r: F64) -> F64:
        return cast(F64, apply_blocks(self.inv_blocks, r) + self.coarse(r))


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


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    """How one recovery went: the method, PCG iterations, features in the local solve, final error estimate (m)."""

    method: str  # "local", "pcg", "direct" or "none"
    iterations: int
    region: int
    error_m: float


class Recovery:
    """The recovered state ``x`` (2N,) of an information matrix, kept with its residual ``r = i - I x``.

    Modes: ``"pcg"`` solves the whole system by warm-started block-Jacobi PCG after every
    update, falling back to a direct solve when PCG does not converge and after a loop closure
    ([1]_ section 3.3); ``"direct"`` always solves directly (reference); ``"local"``:

    - per update, an exact solve on the updated features together with every feature whose
      error estimate exceeds ``local_tol_m`` (those are always next to an earlier local solve),
      then on that region grown by the features it left above the tolerance and their
      neighbours, up to ``max_hops`` times and LOCAL_MAX_FEATURES features. This keeps the
      geometry near the robot exact, but not the smooth, map-wide part of the correction (a
      slight rotation or shift of the whole neighbourhood relative to I^-1 i), which the
      block-Jacobi estimate does not see;
    - every ``global_every`` updates (when positive), and when the local solve is not enough,
      a global solve: PCG warm-started from the current x with the two-level preconditioner
      of :class:`TwoLevel`, which converges in a few tens of iterations whatever N (O(N) each);
      a direct solve after a loop closure or when PCG does not converge.
    """

    def __init__(self, info: InformationMatrix, mode: str, tol_m: float, local_tol_m: float, max_hops: int,
                 maxiter: int, global_every: int) -> None:
        self.info = info
        self.mode, self.tol_m, self.local_tol_m = mode, tol_m, local_tol_m
        self.max_hops, self.maxiter, self.global_every = max_hops, maxiter, global_every
        self.n = 0
        self._x = np.zeros(64)
        self._r = np.zeros(64)
        self._inv = np.zeros((32, 2, 2))
        self._err = np.zeros(32)  # per feature: block-Jacobi error estimate of r
        self._local = np.full(32, -1, dtype=np.int64)  # scratch: feature -> position in the region
        self.dirty: set[int] = set()  # features whose error estimate exceeds local_tol_m
        self.hop_growth = True
        self.changed: list[int] | None = []  # features the last recovery moved (None: possibly all)
        self._last_err = 0.0  # largest error estimate the last local solve left on O's neighbours
        self._since_global = 0
        self.factorizations = 0

    @property
    def x(self) -> F64:
        """The recovered state (2N,) (a view)."""
        return self._x[: 2 * self.n]

    @property
    def r(self) -> F64:
        """The residual ``i - I x`` (2N,) (a view)."""
        return self._r[: 2 * self.n]

    @property
    def inv_blocks(self) -> F64:
        """Inverses of the diagonal blocks of I (N, 2, 2) (a view): the block-Jacobi preconditioner."""
        return self._inv[: self.n]

    @property
    def nbytes(self) -> int:
        """Bytes of the state arrays: O(N)."""
        return self._x.nbytes + self._r.nbytes + self._inv.nbytes + self._err.nbytes + self._local.nbytes

    def grow(self, positions: F64) -> None:
        """Append features (k, 2) at these initial estimates (their residual is 0: I and i are 0 there)."""
        k = len(positions)
        n = self.n + k
        self._x, self._r = _grown(self._x, 2 * n), _grown(self._r, 2 * n)
        self._inv, self._err = _grown(self._inv, n), _grown(self._err, n)
        if len(self._local) < n:
            self._local = np.concatenate([self._local, np.full(max(n, len(self._local)), -1, dtype=np.int64)])
        self._x[2 * self.n:2 * n] = np.asarray(positions, dtype=np.float64).reshape(-1)
        self.n = n

    def set_state(self, x: F64) -> None:
        """Take ``x`` (2N,) as the estimate: recompute the residual, the error estimates and the set (O(N))."""
        self._x[: 2 * self.n] = x
        self._r[: 2 * self.n] = self.info.vector - self.info.matvec(np.array(x))
        self._inv[: self.n] = invert_blocks(self.info.diagonal_blocks())
        err = block_errors(self.inv_blocks, self.r)
        self._err[: self.n] = err
        self.dirty = set(np.flatnonzero(err > self.local_tol_m).tolist())
        self.changed = None
        self._since_global = 0

    def _track(self, features: I64) -> float:
        """Refresh the error estimate of ``features`` and their membership of the set above tolerance.

        Returns the largest of their error estimates.
        """
        r = self._r.reshape(-1, 2)[features]
        err = np.max(np.abs(np.einsum("nij,nj->ni", self._inv[features], r)), axis=1)
        self._err[features] = err
        above = err > self.local_tol_m
        fl = features.tolist()
        self.dirty.update(f for f, a in zip(fl, above.tolist(), strict=True) if a)
        self.dirty.difference_update(f for f, a in zip(fl, above.tolist(), strict=True) if not a)
        return float(err.max()) if len(err) else 0.0

    def record(self, features: I64, d_matrix: F64, d_vector: F64) -> None:
        """Account for ``info.add(features, d_matrix, d_vector)``, which must already have been applied."""
        idx = dofs(features)
        self._r[idx] += d_vector - d_matrix @ self._x[idx]
        self._inv[features] = invert_blocks(self.info.diagonal_blocks(features))
        self._track(np.asarray(features, dtype=np.int64))

    def error(self) -> float:
        """Block-Jacobi estimate of the largest remaining correction of any feature (m); O(N)."""
        return float(self._err[: self.n].max()) if self.n else 0.0

    def local_solve(self, region: list[int]) -> None:
        """Solve ``I_OO d = r_O`` on the features ``region`` (O), then ``x_O += d`` and ``r -= I[:, O] d``.

        Exact on O (r_O becomes 0); the residual moves to O's neighbours. O(blocks of O's rows).
        """
        k = len(region)
        feats = np.asarray(region, dtype=np.int64)
        pos, cols, vals = self.info.row_blocks(region)
        self._local[feats] = np.arange(k)
        lq = self._local[cols]
        self._local[feats] = -1
        inside = lq >= 0
        block = np.zeros((k, k, 2, 2))
        block[pos[inside], lq[inside]] = vals[inside]
        a = block.transpose(0, 2, 1, 3).reshape(2 * k, 2 * k)
        idx = dofs(feats)
        chol = sla.cho_factor(0.5 * (a + a.T), check_finite=False)
        delta = sla.cho_solve(chol, self._r[idx], check_finite=False)
        self._x[idx] += delta
        self._r[idx] = 0.0
        out = ~inside
        if out.any():
            g = cols[out]
            d = delta.reshape(-1, 2)[pos[out]]
            push = np.einsum("nji,nj->ni", vals[out], d)  # I_gf d_f = (I_fg)^T d_f
            r2 = self._r.reshape(-1, 2)
            np.subtract.at(r2, g, push)
            self._last_err = self._track(np.unique(g))
        else:
            self._last_err = 0.0
        self._err[feats] = 0.0
        self.dirty.difference_update(region)

    def solve_direct(self) -> RecoveryReport:
        """x = I^-1 i by sparse LU."""
        if self.n == 0:
            return RecoveryReport("none", 0, 0, 0.0)
        self.factorizations += 1
        self.set_state(direct(self.info, np.array(self.info.vector)))
        return RecoveryReport("direct", 0, 0, self.error())

    def _solve_pcg(self) -> RecoveryReport:
        result = pcg(self.info, np.array(self.info.vector), np.array(self.x), self.inv_blocks, self.tol_m,
                     self.maxiter)
        if not result.converged:
            self.solve_direct()
            return RecoveryReport("direct", result.iterations, 0, self.error())
        self.set_state(result.x)
        return RecoveryReport("pcg", result.iterations, 0, self.error())

    def _solve_global(self, loop_closure: bool) -> RecoveryReport:
        """Warm-started two-level PCG (:class:`TwoLevel`); a direct solve after a loop closure or if it fails."""
        if loop_closure:
            return self.solve_direct()
        result = pcg(self.info, np.array(self.info.vector), np.array(self.x), self.inv_blocks, self.tol_m,
                     self.maxiter, TwoLevel(self.info, self.inv_blocks, self.x))
        if not result.converged:
            self.solve_direct()
            return RecoveryReport("direct", result.iterations, 0, self.error())
        self.set_state(result.x)
        return RecoveryReport("pcg", result.iterations, 0, self.error())

    def solve(self, touched: list[int], loop_closure: bool) -> RecoveryReport:
        """Recover x after an update of the features ``touched`` (class docstring for the modes)."""
        self._since_global += 1
        if self.mode == "direct" or (loop_closure and self.mode == "pcg"):
            return self.solve_direct()
        if self.mode == "pcg":
            return self._solve_pcg()
        if 0 < self.global_every <= self._since_global:
            return self._solve_global(False)
        region = set(touched) | self.dirty
        solved: set[int] = set()
        for _ in range(self.max_hops):
            if len(region) > LOCAL_MAX_FEATURES:
                break  # a region too large for a dense solve: PCG instead
            self.local_solve(sorted(region))
            solved |= region
            if not self.dirty:
                self.changed = sorted(solved)
                return RecoveryReport("local", 0, len(region), self._last_err)
            grow = set(self.dirty)
            if self.hop_growth:
                for f in self.dirty:
                    grow |= self.info.neighbours[f]
            region |= grow
        return self._solve_global(loop_closure)
