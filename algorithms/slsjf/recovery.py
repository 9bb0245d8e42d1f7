"""SLSJF's state and covariance recovery by preconditioned CG, the way D-SLAM recovers its map.

The global map's estimate solves ``I x = i`` and a covariance column solves ``I c = e_j``. SLSJF [1]_
does both with a sparse Cholesky factor of ``I``, redone at every join: its fill, and so its time and
memory, grow faster than the map (``benchmarks/slsjf_scaling.py``). D-SLAM [2]_ (sections 3.2-3.3)
recovers its map instead with "a set of sparse linear equations, using few iterations requiring O(N)
operations as a good initial guess is always available", and "the desired columns of the covariance
matrix ... by solving a constant number of sparse linear equations with the aid of a good initial
guess". ``GlobalMap(recovery="pcg")`` does that for SLSJF (a named departure from [1]_):

- the estimate: preconditioned CG from the estimate before the join (the new local map's variables
  initialised from it), each iteration one sparse product, O(nonzeros of I) = O(map);
- a covariance column: preconditioned CG from the same column at the previous join (a join changes I
  near one local map only), else from zero;
- the preconditioner: D-SLAM's two-level one (:class:`slamreplay.algorithms.dslam.recovery.TwoLevel`)
  for SLSJF's state, block-Jacobi on the 3x3 pose and 2x2 feature blocks of ``I`` plus the rigid
  motions of square cells of poses and features (D-SLAM's coarse space, with poses);
- the stopping rule: D-SLAM's, no entry of the preconditioned residual above the tolerance (m, rad for
  the estimate; relative to the entry's block-Jacobi variance for a covariance column).

Nothing here holds a factor of ``I``: the memory is I's nonzeros, the estimate, the preconditioner (I's
diagonal blocks and a coarse matrix about a tenth of the state) and the columns kept as initial guesses.

References
----------
.. [1] S. Huang, Z. Wang, G. Dissanayake, "Sparse local submap joining filter for building large-scale
   maps", IEEE Transactions on Robotics 24(5), 2008.
.. [2] Z. Wang, S. Huang, G. Dissanayake, "Implementation issues and experimental evaluation of D-SLAM",
   FSR 2005, sections 3.2-3.3.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from slamreplay.algorithms.dslam.recovery import COARSE_CELL_M, Coarse, coarse_space

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class Matrix:
    """A sparse symmetric matrix as the operator :func:`slamreplay.algorithms.dslam.recovery.pcg` multiplies by."""

    def __init__(self, a: sp.spmatrix) -> None:
        self.a = sp.csr_matrix(a)

    def matvec(self, x: F64) -> F64:
        return cast(F64, np.asarray(self.a @ x))


def _blocks(a: sp.csr_matrix, offsets: I64, size: int) -> F64:
    """The diagonal blocks (k, size, size) of ``a`` starting at ``offsets``."""
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    rows = (offsets[:, None, None] + i).reshape(-1)
    cols = (offsets[:, None, None] + j).reshape(-1)
    return np.asarray(a[rows, cols], np.float64).reshape(len(offsets), size, size)


def block_jacobi(a: sp.spmatrix, poses: I64, features: I64) -> sp.csr_matrix:
    """The inverse of the block diagonal of ``a``: 3x3 blocks at the pose offsets, 2x2 at the feature offsets."""
    a = sp.csr_matrix(a)
    rows, cols, vals = [], [], []
    for offsets, size in ((poses, 3), (features, 2)):
        if not len(offsets):
            continue
        inv = np.linalg.inv(_blocks(a, offsets, size))
        i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
        rows.append((offsets[:, None, None] + i).reshape(-1))
        cols.append((offsets[:, None, None] + j).reshape(-1))
        vals.append(inv.reshape(-1))
    n = a.shape[0]
    if not rows:
        return sp.csr_matrix((n, n))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


class TwoLevel:
    """``M^-1 = D^-1 + P (P^T I P)^-1 P^T`` for SLSJF's state: D its 3x3 and 2x2 diagonal blocks, P the rigid
    motions of cells of poses and features (D-SLAM's :func:`~slamreplay.algorithms.dslam.recovery.coarse_space`
    with poses). The coarse part takes the map-wide, smooth part of the error (a loop closing moves whole
    neighbourhoods), which block-Jacobi alone would leave to hundreds of iterations."""

    def __init__(self, a: sp.spmatrix, x: F64, poses: I64, features: I64, cell_m: float = COARSE_CELL_M) -> None:
        a = sp.csr_matrix(a)
        self.d_inv = block_jacobi(a, poses, features)
        self.coarse = Coarse(a, coarse_space(x, cell_m, poses, features))

    def variances(self) -> F64:
        """The diagonal of D^-1 (each entry's variance given its own block alone: a lower bound on its marginal)."""
        return np.asarray(self.d_inv.diagonal(), np.float64)

    def __call__(self, r: F64) -> F64:
        return np.asarray(self.d_inv @ r, np.float64) + self.coarse(r)

    @property
    def nbytes(self) -> int:
        d = self.d_inv
        return int(d.data.nbytes + d.indices.nbytes + d.indptr.nbytes) + self.coarse.nbytes
