"""Block-sparse normal equations of a graph problem, and a sparse Cholesky that keeps its analysis.

:class:`BlockSystem` does the symbolic work once per graph structure: a fill-reducing ordering of
the vertex blocks and, for every (edge, block, row, column) contribution, its slot in the CSC
data array. Each iteration then only fills numbers with ``np.bincount`` [1]_.

:class:`SparseCholesky` keeps the symbolic work of its factorization (ordering, analysis) for every
later matrix with the same pattern, and picks, in this order:

- CHOLMOD through scikit-sparse (``sksparse``) when it is importable (the ``cholmod`` extra, built
  against the system's SuiteSparse);
- CHOLMOD through CVXOPT's ``cvxopt.cholmod``, which installs from a wheel with SuiteSparse inside (the
  ``solver`` extra: not a core dependency, as CVXOPT is GPL-3.0 and slamreplay MIT);
- QDLDL (``qdldl``, Apache-2.0, a core dependency from a wheel): an up-looking LDL' after its own AMD
  ordering, ``update`` re-factoring in place with the ordering and elimination tree kept. It reads the
  upper triangle, which :class:`BlockSystem` lays out directly (``upper``);
- SciPy's SuperLU on the already-permuted matrix with the natural ordering and no pivoting, the fastest
  SciPy path measured here (the ordering is the only symbolic step SciPy lets us reuse), where neither
  imports.

Measured on the first normal equations of M3500 / intel / city10000 (CPU ms, numeric factorization +
solve, one run on a shared 2-core machine): CVXOPT 3.7 / 1.2 / 18.2, QDLDL 3.5 / 0.9 / 34.2, SciPy
SuperLU 9.2 / 2.5 / 64.0, cholespy 16.6 / 5.8 / 90.0 (cholespy has no reuse of the analysis: each
factorization starts over). QDLDL's first factorization, its AMD included, 7.7 / 2.7 / 49.8 against
CVXOPT's 9.0 / 2.6 / 31.6 (CHOLMOD is supernodal on the larger two: QDLDL has no supernodes).

References
----------
.. [1] R. Kümmerle et al., "g2o: A general framework for graph optimization", ICRA 2011, sec. III-C.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
Backend = Literal["auto", "cholmod", "qdldl", "superlu"]

try:  # optional: CHOLMOD where SuiteSparse and scikit-sparse are installed
    from sksparse.cholmod import analyze as _cholmod_analyze  # type: ignore[import-not-found, unused-ignore]
except ImportError:
    _cholmod_analyze = None
try:  # CHOLMOD and AMD from CVXOPT's wheel (the solver extra)
    from cvxopt import amd as _cvx_amd  # type: ignore[import-untyped, unused-ignore]
    from cvxopt import cholmod as _cvx_cholmod  # type: ignore[import-untyped, unused-ignore]
    from cvxopt import matrix as _cvx_matrix  # type: ignore[import-untyped, unused-ignore]
    from cvxopt import spmatrix as _cvx_spmatrix  # type: ignore[import-untyped, unused-ignore]
except ImportError:  # the install keeps working on SciPy alone
    _cvx_cholmod = None

try:  # QDLDL (Apache-2.0): an LDL' with AMD inside, from a wheel; a core dependency
    import qdldl as _qdldl  # type: ignore[import-untyped, unused-ignore]
except ImportError:  # a platform without its wheel keeps working on SciPy alone
    _qdldl = None

HAVE_CVXOPT = _cvx_cholmod is not None
HAVE_QDLDL = _qdldl is not None
HAVE_CHOLMOD = _cholmod_analyze is not None or HAVE_CVXOPT
_cholmod_order = _cholmod_analyze  # the ordering's own handle (tests fake the factorization's)
# CVXOPT's CHOLMOD: supernodal (BLAS) factorization from this many unknowns, simplicial below.
# Measured (CPU ms, numeric factorization / symbolic analysis / solve, the pose-block AMD order):
# intel (5,181 unknowns) simplicial 1.05 / 1.16 / 0.07, supernodal 1.07 / 1.52 / 0.23;
# M3500 (10,497) simplicial 4.0 / 3.0 / 0.2, supernodal 3.2 / 3.5 / 0.5; city10000 (29,997)
# simplicial 45 / 15 / 3, supernodal 15 / 24 / 3. CHOLMOD's own choice (flops / nnz(L) >= 40)
# picks simplicial for M3500 too.
SUPERNODAL_MIN_SIZE = 8000
# QDLDL: the largest normwise backward error a solve may have (SparseCholesky.solve). LDL' without pivoting
# on the optimizer's positive semi-definite matrices gives about n eps; a factor left half from an older
# matrix (a zero pivot) gives order 1.
QDLDL_TOL = 1e-8


def _cvx_lower(h: sp.csc_matrix) -> tuple[Any, I64]:
    """A CVXOPT sparse matrix holding the lower triangle of ``h`` (all CHOLMOD reads of a symmetric
    matrix: half the entries to copy each time), and the positions of those entries in ``h.data``;
    its values sit in CSC order, as in ``h`` (whose row indices are sorted within each column)."""
    n = h.shape[0]
    cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(h.indptr))
    low = np.flatnonzero(h.indices >= cols)
    a = _cvx_spmatrix(_cvx_matrix(np.asarray(h.data, np.float64)[low]), _cvx_matrix(h.indices[low].astype(np.int64)),
                      _cvx_matrix(cols[low]), (n, n))
    return a, low


def _block_ordering(n_free: int, rows: I64, cols: I64) -> I64:
    """Fill-reducing block order (CHOLMOD's AMD, else SuperLU's minimum degree); returns pos."""
    if n_free <= 2:
        return np.arange(n_free, dtype=np.int64)
    off = rows != cols
    r, c = rows[off], cols[off]
    deg = np.bincount(r, minlength=n_free).astype(np.float64)

    def pattern() -> sp.csc_matrix:
        """A diagonally dominant matrix with the block pattern: its fill-reducing order is what we want."""
        return sp.csc_matrix(
            (np.r_[-np.ones(r.size), deg + 1.0], (np.r_[r, np.arange(n_free)], np.r_[c, np.arange(n_free)])),
            shape=(n_free, n_free),
        )

    if _cholmod_order is not None or HAVE_CVXOPT:
        # AMD on the block graph: 3x faster than SuperLU's MMD and 2-20 % less fill (M3500, city10000)
        if _cholmod_order is not None:
            perm = np.asarray(_cholmod_order(pattern(), mode="simplicial", ordering_method="amd").P(),
                              dtype=np.int64)
        else:
            low = np.flatnonzero(r > c)  # the pattern's lower triangle and diagonal is all AMD reads
            diag = np.arange(n_free, dtype=np.int64)
            lower = _cvx_spmatrix(1.0, _cvx_matrix(np.r_[r[low], diag].astype(np.int64)),
                                  _cvx_matrix(np.r_[c[low], diag].astype(np.int64)), (n_free, n_free))
            perm = np.asarray(_cvx_amd.order(lower), dtype=np.int64).ravel()
        pos = np.empty(n_free, dtype=np.int64)
        pos[perm] = np.arange(n_free)
        return pos
    lu = sla.splu(pattern(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return np.asarray(lu.perm_c, dtype=np.int64)  # perm_c[v] is the new position of block v


class BlockSystem:
    """Structure of ``H = sum_k J_k^T W_k J_k`` for edges (i_k, j_k) between d-dimensional blocks.

    Parameters
    ----------
    n_vertices : int
    i, j : (m,) int64
        Edge endpoints, vertex indices in ``[0, n_vertices)``.
    fixed : int or sequence of int
        The gauge vertex (or vertices), whose blocks are removed from the system.
    dim : int
        Block size (3 for SE(2) poses).
    order : (n_vertices - n_fixed,) int64, optional
        Block position of each free vertex (in vertex order), e.g. a previous system's ``pos``
        extended by new vertices; computed (minimum degree) when None.
    lower : bool
        Store only the lower triangle (what CHOLMOD reads of a symmetric matrix): about half the
        entries to fill and copy per iteration; ``matrix`` then returns that triangle.
    upper : bool
        Store only the upper triangle (what QDLDL reads), in CSC order: the lower layout
        transposed once here, so each iteration costs what ``lower`` costs.
    """

    def __init__(self, n_vertices: int, i: I64, j: I64, fixed: int | tuple[int, ...], dim: int = 3,
                 order: I64 | None = None, lower: bool = False, upper: bool = False) -> None:
        if lower and upper:
            raise ValueError("lower and upper exclude each other (neither: the full matrix)")
        half = lower or upper
        d = dim
        free = np.ones(n_vertices, dtype=bool)
        free[np.asarray(fixed, dtype=np.int64)] = False
        n_free = int(free.sum())
        if order is None:
            idx = np.cumsum(free) - 1
            both = free[i] & free[j]
            a, b = idx[i[both]], idx[j[both]]
            order = _block_ordering(n_free, np.r_[a, b], np.r_[b, a])
        elif order.shape != (n_free,):
            raise ValueError(f"order must have shape ({n_free},), got {order.shape}")
        pos = np.full(n_vertices, -1, dtype=np.int64)
        pos[free] = order
        p, q = pos[i], pos[j]
        off = (p >= 0) & (q >= 0)
        hi, lo = np.maximum(p[off], q[off]), np.minimum(p[off], q[off])
        # column-major block keys (col * n + row), CSC order after sorting: every diagonal block,
        # then the off-diagonal blocks of the edges: (hi, lo) below the diagonal unless upper,
        # (lo, hi) above it unless lower
        diag_keys = np.arange(n_free, dtype=np.int64) * (n_free + 1)
        keys = (np.r_[diag_keys, lo * n_free + hi] if lower else np.r_[diag_keys, hi * n_free + lo] if upper
                else np.r_[diag_keys, lo * n_free + hi, hi * n_free + lo])
        ukeys, inv = np.unique(keys, return_inverse=True)
        ucol, urow = ukeys // n_free, ukeys % n_free
        cnt = np.bincount(ucol, minlength=n_free)
        bstart = np.r_[0, np.cumsum(cnt)]
        rank = np.arange(ukeys.size) - bstart[ucol]
        n_u = ukeys.size
        rr, cc = np.arange(d)[:, None, None], np.arange(d)[None, :, None]
        # sl[r, c, t]: data position of entry (r, c) of unique block t (entry-major, so per-edge
        # gathers come out edge-last); column t = n_u is a sentinel for absent blocks (nnz: dropped).
        # lower: a diagonal block keeps r >= c only and is the first of its block column, so scalar
        # column c of block column k holds d * cnt[k] - c entries; upper: it keeps r <= c and is the
        # last, d * cnt[k] - (d - 1 - c) entries. drop: the entries of the block column's diagonal
        # block dropped before entry (r, c) in CSC order
        tri = d * (d - 1) // 2 if half else 0
        cstart = np.r_[0, np.cumsum(d * d * cnt - tri)]
        nnz = int(cstart[-1])
        drop = (cc * (cc - 1) // 2 + cc if lower else cc * (d - 1) - cc * (cc - 1) // 2 if upper else 0 * cc)
        sl = np.empty((d, d, n_u + 1), dtype=np.int64)
        sl[:, :, :n_u] = (cstart[ucol] + d * rank) + cc * d * cnt[ucol] + rr - drop
        sl[:, :, n_u] = nnz
        if half:
            isdiag = np.flatnonzero(urow == ucol)
            for r, c in zip(*np.triu_indices(d, 1), strict=True):
                if upper:
                    r, c = c, r
                sl[r, c, isdiag] = nnz  # the other half of a diagonal block
        indices = np.empty(nnz + 1, dtype=np.int32)  # [nnz]: where the dropped entries land
        indices[sl[:, :, :n_u].ravel()] = np.broadcast_to(d * urow + rr, (d, d, n_u)).ravel()
        indices = indices[:nnz]
        per_col = np.repeat(d * cnt, d) - (np.tile(np.arange(d), n_free) if lower
                                            else np.tile(np.arange(d)[::-1], n_free) if upper else 0)
        colptr = np.r_[0, np.cumsum(per_col)].astype(np.int32)
        # per edge (edge last): blocks (p, p), (p, q), (q, q); (p, q) is stored transposed where p is above q
        # (upper: below q)
        m = i.size
        tdiag = np.r_[inv[:n_free], n_u]  # [-1] (a fixed endpoint) is the sentinel
        toff = np.full(m, n_u, dtype=np.int64)
        toff[off] = inv[n_free : n_free + lo.size]  # block (hi, lo); upper: (lo, hi)
        below = p > q
        slot_h = np.empty((3 if half else 4, d, d, m), dtype=np.int64)
        sl.take(tdiag[p], axis=2, out=slot_h[0])
        sl.take(toff, axis=2, out=slot_h[1])
        np.copyto(slot_h[1], slot_h[1].transpose(1, 0, 2).copy(), where=below if upper else ~below)
        sl.take(tdiag[q], axis=2, out=slot_h[2])
        if not half:  # the mirror block (lo, hi) of the full matrix gets H_pq^T: a 4th group
            toff[off] = inv[n_free + lo.size :]
            sl.take(toff, axis=2, out=slot_h[3])
            np.copyto(slot_h[3], slot_h[3].transpose(1, 0, 2).copy(), where=below)
        slot_b = np.stack([np.where(p >= 0, d * p, d * n_free), np.where(q >= 0, d * q, d * n_free)])
        ar = np.arange(d)
        diag_slots = sl[ar, ar][:, tdiag[:-1]].T.ravel()
        slot_h = slot_h.ravel()
        self.dim = d
        self.size = d * n_free
        self.nnz = nnz
        self.lower = lower
        self.upper = upper
        self.pos: I64 = pos
        self._indices = indices
        self._indptr = colptr
        self._slot_h = slot_h  # (group, d, d, edge)
        self._slot_b = (slot_b[:, None, :] + rr[:, :, 0][None]).ravel()  # (2, d, edge)
        self.diag_slots: I64 = diag_slots
        self.n_edges = int(m)

    def matrix(self, data: F64) -> sp.csc_matrix:
        """CSC matrix with this structure and the given data (shares the index arrays); the lower
        (upper) triangle only when built with ``lower`` (``upper``)."""
        m = sp.csc_matrix((self.size, self.size))
        m.data, m.indices, m.indptr = data, self._indices, self._indptr
        return m

    def assemble(self, blocks: F64, grad: F64) -> tuple[F64, F64]:
        """CSC data of H and the vector b, in the permuted order.

        Parameters
        ----------
        blocks : (3, d, d, m) or (4, d, d, m) float64
            Per edge ``J_i^T W J_i``, ``J_i^T W J_j``, ``J_j^T W J_j`` (edge last); a 4-group array
            holds ``J_j^T W J_i`` third, which is not read (it is the transpose of the second).
        grad : (2, d, m) float64
            Per edge ``J_i^T W e`` and ``J_j^T W e``.
        """
        if blocks.shape[0] == 4:
            blocks = blocks[[0, 1, 3]]
        w = blocks.ravel() if self.lower or self.upper else np.concatenate([blocks.ravel(), blocks[1].ravel()])
        data = np.bincount(self._slot_h, weights=w, minlength=self.nnz + 1)[: self.nnz]
        b = np.bincount(self._slot_b, weights=grad.ravel(), minlength=self.size + 1)[: self.size]
        return data.astype(np.float64, copy=False), b.astype(np.float64, copy=False)

    def assemble_gradient(self, grad: F64) -> F64:
        """The vector b alone (see :meth:`assemble`)."""
        b = np.bincount(self._slot_b, weights=grad.ravel(), minlength=self.size + 1)[: self.size]
        return b.astype(np.float64, copy=False)

    def scatter(self, x: F64, n_vertices: int) -> F64:
        """Map a permuted solution vector (size,) back to per-vertex blocks (n, d), 0 at the gauge."""
        out = np.zeros((n_vertices, self.dim))
        free = self.pos >= 0
        out[free] = x.reshape(-1, self.dim)[self.pos[free]]
        return out


class SparseCholesky:
    """Factorizations of SPD matrices that share one sparsity pattern.

    Parameters
    ----------
    backend : {"auto", "cholmod", "qdldl", "superlu"}
        ``auto`` picks CHOLMOD when a binding imports (scikit-sparse, else CVXOPT), else QDLDL (a core
        dependency), else SuperLU.
    """

    def __init__(self, backend: Backend = "auto") -> None:
        if backend not in ("auto", "cholmod", "qdldl", "superlu"):
            raise ValueError(f"backend must be auto, cholmod, qdldl or superlu, got {backend!r}")
        if backend == "cholmod" and not HAVE_CHOLMOD:
            raise ValueError("backend: 'cholmod' requested but neither cvxopt nor scikit-sparse (sksparse) is "
                             "importable: pip install cvxopt")
        if backend == "qdldl" and not HAVE_QDLDL:
            raise ValueError("backend: 'qdldl' requested but qdldl is not importable: pip install qdldl")
        if backend == "auto":
            backend = "cholmod" if HAVE_CHOLMOD else "qdldl" if HAVE_QDLDL else "superlu"
        self.backend = backend
        # which binding runs CHOLMOD: scikit-sparse when installed (the opt-in extra), else CVXOPT's wheel
        self.provider = (backend if backend != "cholmod"
                         else "scikit-sparse" if _cholmod_analyze is not None else "cvxopt")
        self._qd: Any = None  # QDLDL: the solver (its AMD order and elimination tree), refactored in place
        self._u: Any = None  # QDLDL: the upper triangle last factored, its diagonal and max-norm (a solve's check)
        self._diag: F64 = np.zeros(0)
        self._norm = 0.0
        self._up: I64 | None = None  # QDLDL: positions of the upper triangle in the CSC data (None: all of it)
        self._ucols: I64 = np.zeros(0, np.int64)  # QDLDL: the column of each entry of the upper triangle
        self._upattern: tuple[Any, Any] = (None, None)  # QDLDL: its (indices, indptr)
        self._symbolic: Any = None
        self._lu: Any = None
        self._a: Any = None  # CVXOPT: the matrix whose values are replaced before each numeric factorization
        self._low: I64 = np.zeros(0, np.int64)  # CVXOPT: positions of the lower triangle in the CSC data
        self._nnz = -1
        self._qd_n = -1
        self._all = False
        # whether BlockSystem should hand over the lower (upper) triangle only: all CVXOPT's CHOLMOD (QDLDL) reads
        self.wants_lower = self.provider == "cvxopt"
        self.wants_upper = self.provider == "qdldl"
        # QDLDL orders the matrix itself (AMD, once per pattern): a block order of ours would be thrown away
        self.orders_itself = self.provider == "qdldl"

    def factor(self, h: sp.csc_matrix) -> bool:
        """Factor ``h`` (symmetric, already fill-reduced); False when it is singular / not PD.

        CVXOPT below ``SUPERNODAL_MIN_SIZE`` factors LDL' (simplicial), which reports a singular
        matrix but factors an indefinite one; the optimizer's matrices (J^T W J plus a positive
        damping, W >= 0) are positive semi-definite by construction, so singular is the case to catch.
        """
        if self.provider == "scikit-sparse":
            assert _cholmod_analyze is not None
            try:
                if self._symbolic is None:
                    # h is already fill-reduced; simplicial LDL' measured 1.2-2x faster than the
                    # supernodal (BLAS) factor CHOLMOD picks for city10000 on a busy 2-core machine
                    self._symbolic = _cholmod_analyze(h, mode="simplicial", ordering_method="natural")
                self._symbolic.cholesky_inplace(h)
            except Exception:  # noqa: BLE001 - CholmodNotPositiveDefiniteError and friends
                return False
            return True
        if self.provider == "cvxopt":
            if self._a is None or self._a.size != h.shape or self._nnz != h.nnz:
                self._a, self._low = _cvx_lower(h)
                self._nnz = h.nnz
                self._all = self._low.size == h.nnz  # h is the lower triangle already (BlockSystem(lower=True))
                # h is already fill-reduced: the identity permutation keeps that order; the analysis is
                # done here once and reused (cholmod.numeric) for every matrix with this pattern
                saved = dict(_cvx_cholmod.options)
                _cvx_cholmod.options["supernodal"] = 2 if h.shape[0] >= SUPERNODAL_MIN_SIZE else 0
                # the given order only: by default CHOLMOD also tries its own AMD and keeps the better,
                # which doubled the analysis time (intel 1.75 -> 0.50 ms, M3500 3.7 -> 1.8 ms, city10000
                # 13 -> 9 ms) for the same numeric factorization time
                _cvx_cholmod.options["nmethods"] = 1
                try:
                    identity = _cvx_matrix(np.arange(h.shape[0], dtype=np.int64))
                    self._symbolic = _cvx_cholmod.symbolic(self._a, p=identity)
                finally:  # CVXOPT's options are module state: leave them as found
                    _cvx_cholmod.options.clear()
                    _cvx_cholmod.options.update(saved)
            else:
                v = np.asarray(h.data, np.float64)
                self._a.V = _cvx_matrix(v if self._all else v[self._low])
            try:
                _cvx_cholmod.numeric(self._a, self._symbolic)
            except ArithmeticError:  # not positive definite
                return False
            return True
        if self.provider == "qdldl":
            return self._factor_qdldl(h)
        try:
            # relax=1, panel_size=1 measured 35 % faster than SuperLU's defaults on M3500, intel and
            # city10000; large values (relax 16, panel 32) crash SciPy 1.17's SuperLU.
            self._lu = sla.splu(
                h, permc_spec="NATURAL", diag_pivot_thresh=0.0, relax=1, panel_size=1,
                options={"SymmetricMode": True},
            )
        except RuntimeError:  # "Factor is exactly singular"
            return False
        return True

    def _factor_qdldl(self, h: sp.csc_matrix) -> bool:
        """QDLDL: AMD, elimination tree and numeric factorization for a new pattern, the numeric one alone
        (``update``, in place) for the same pattern."""
        assert _qdldl is not None
        n = h.shape[0]
        if n == 0:
            return False
        new = self._qd is None or self._nnz != h.nnz or self._qd_n != n
        if new:  # the upper triangle's pattern, and where its entries sit in h's data (None: all of them)
            cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(h.indptr))
            keep = h.indices <= cols
            self._up = None if keep.all() else np.flatnonzero(keep)
            self._nnz, self._qd_n = h.nnz, n
            self._ucols = cols if self._up is None else cols[self._up]
            indptr = h.indptr if self._up is None else np.r_[0, np.cumsum(np.bincount(self._ucols, minlength=n))]
            self._upattern = (h.indices if self._up is None else h.indices[self._up], indptr)
        u = h if self._up is None else sp.csc_matrix(
            (np.asarray(h.data, np.float64)[self._up], *self._upattern), shape=h.shape)
        if new:
            try:
                self._qd = _qdldl.Solver(u, upper=True)
            except (RuntimeError, ValueError):  # a zero pivot: singular
                self._qd = None
                return False
        else:
            self._qd.update(u, upper=True)
        self._u, self._diag = u, u.diagonal()
        a = np.abs(u.data)
        rowsum = np.bincount(u.indices, a, n) + np.bincount(self._ucols, a, n) - np.abs(self._diag)
        self._norm = float(rowsum.max())  # |H| in the max norm, H = U + U^T - diag(U)
        return True

    def solve(self, rhs: F64) -> F64:
        """Solve with the last successful factorization; rhs (N,) or (N, k).

        QDLDL's re-factorization (same pattern, new numbers) does not report a zero pivot: it stops there
        and leaves the rest of the factor from the previous matrix. So a QDLDL solve checks its normwise
        backward error, ``|H x - b| <= QDLDL_TOL (|H| |x| + |b|)`` in the max norm (two products with the
        triangle), and raises ``np.linalg.LinAlgError`` instead of returning a wrong answer.
        """
        if self.provider == "qdldl":
            r = np.asarray(rhs, np.float64)
            if r.ndim == 1:
                x = np.asarray(self._qd.solve(r), dtype=np.float64)
            else:
                x = np.column_stack([self._qd.solve(np.ascontiguousarray(r[:, k])) for k in range(r.shape[1])])
            u = self._u
            res = u @ x + u.T @ x - self._diag.reshape((-1,) + (1,) * (x.ndim - 1)) * x - r
            scale = self._norm * np.max(np.abs(x), initial=0.0) + np.max(np.abs(r), initial=0.0)
            if not (np.all(np.isfinite(x)) and np.max(np.abs(res), initial=0.0) <= QDLDL_TOL * scale):
                raise np.linalg.LinAlgError("singular matrix: a zero pivot in the LDL' factorization")
            return x
        if self.provider == "scikit-sparse":
            return np.asarray(self._symbolic(rhs), dtype=np.float64)
        if self.provider == "cvxopt":
            r = np.asarray(rhs, np.float64)
            b = _cvx_matrix(np.asfortranarray(r.reshape(r.shape[0], -1)))
            _cvx_cholmod.solve(self._symbolic, b)  # in place
            return np.array(b, dtype=np.float64).reshape(r.shape)
        return np.asarray(self._lu.solve(np.ascontiguousarray(rhs)), dtype=np.float64)
