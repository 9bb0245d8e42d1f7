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
  motions of square cells of poses and features (:func:`coarse_space`);
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
import scipy.sparse.linalg as sla
from numpy.typing import NDArray

from slamreplay.algorithms.dslam.recovery import COARSE_CELL_M

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


def coarse_space(x: F64, poses: I64, features: I64, cell_m: float) -> sp.csr_matrix:
    """The prolongation P (n, 3C): each square cell of side ``cell_m`` moves its poses and features rigidly.

    D-SLAM's coarse space (:func:`slamreplay.algorithms.dslam.recovery.coarse_space`) with poses in it: a
    variable belongs to the cell holding its position; a cell's columns are its translations in x and y and
    its rotation about its centroid (lever arms scaled by ``1 / cell_m``), which turns a pose's heading by the
    same angle. A cell of a single feature has no rotation column.
    """
    offsets = np.concatenate([poses, features]).astype(np.int64)
    is_pose = np.concatenate([np.ones(len(poses), bool), np.zeros(len(features), bool)])
    n, v = len(x), len(offsets)
    if v == 0:
        return sp.csr_matrix((n, 0))
    pts = np.stack([x[offsets], x[offsets + 1]], -1)
    _, agg = np.unique(np.floor(pts / cell_m).astype(np.int64), axis=0, return_inverse=True)
    agg = agg.reshape(-1)
    c = int(agg.max()) + 1
    counts = np.bincount(agg, minlength=c)
    has_pose = np.bincount(agg, is_pose.astype(np.float64), c) > 0
    cent = np.stack([np.bincount(agg, pts[:, 0], c), np.bincount(agg, pts[:, 1], c)], -1) / counts[:, None]
    lever = (pts - cent[agg]) / cell_m
    rotates = (counts >= 2) | has_pose
    rot = np.cumsum(rotates) - 1  # the rotation column of each cell that has one
    r = rotates[agg]
    rot_col = 2 * c + rot[agg[r]]
    p = is_pose & r
    rows = np.concatenate([offsets, offsets + 1, offsets[r], offsets[r] + 1, offsets[p] + 2])
    cols = np.concatenate([2 * agg, 2 * agg + 1, rot_col, rot_col, 2 * c + rot[agg[p]]])
    vals = np.concatenate([np.ones(2 * v), -lever[r, 1], lever[r, 0], np.full(int(p.sum()), 1.0 / cell_m)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, 2 * c + int(rotates.sum())))


class TwoLevel:
    """``M^-1 = D^-1 + P (P^T I P)^-1 P^T`` for SLSJF's state (D: its 3x3 and 2x2 diagonal blocks; P:
    :func:`coarse_space`). The coarse part takes the map-wide, smooth part of the error (a loop closing
    moves whole neighbourhoods), which block-Jacobi alone would leave to hundreds of iterations."""

    def __init__(self, a: sp.spmatrix, x: F64, poses: I64, features: I64, cell_m: float = COARSE_CELL_M) -> None:
        a = sp.csr_matrix(a)
        self.d_inv = block_jacobi(a, poses, features)
        self.p = coarse_space(x, poses, features, cell_m)
        self.pt = self.p.T.tocsr()
        coarse = (self.pt @ (a @ self.p)).tocsc()
        self.lu = sla.splu(0.5 * (coarse + coarse.T), permc_spec="MMD_AT_PLUS_A") if coarse.shape[0] else None

    def variances(self) -> F64:
        """The diagonal of D^-1 (each entry's variance given its own block alone: a lower bound on its marginal)."""
        return np.asarray(self.d_inv.diagonal(), np.float64)

    def __call__(self, r: F64) -> F64:
        out = np.asarray(self.d_inv @ r, np.float64)
        if self.lu is not None:
            out = out + np.asarray(self.p @ np.asarray(self.lu.solve(np.asarray(self.pt @ r))), np.float64)
        return out

    @property
    def nbytes(self) -> int:
        mats = (self.d_inv, self.p, self.pt)
        held = sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes for m in mats)
        if self.lu is not None:
            held += sum(m.data.nbytes + m.indices.nbytes + m.indptr.nbytes for m in (self.lu.L, self.lu.U))
        return int(held)
