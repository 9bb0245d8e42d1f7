"""Analysis of an optimized pose graph: marginal covariances and trajectory error against truth.

References
----------
.. [1] R. Kümmerle et al., "g2o: A general framework for graph optimization", ICRA 2011
   (``SparseOptimizer::computeMarginals`` solves for the needed blocks of the inverse only).
.. [2] S. Umeyama, "Least-squares estimation of transformation parameters between two point
   patterns", IEEE TPAMI 13(4), 1991 (without scale here).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common.posegraph import OptimizerConfig, PoseGraph, _Problem

F64 = NDArray[np.float64]


def marginal_covariances(graph: PoseGraph, vertices: ArrayLike, cfg: OptimizerConfig | None = None,
                         batch: int = 128) -> F64:
    """Marginal 3x3 covariances of chosen poses, relative to the gauge, at ``graph.poses``.

    Factors H = J^T W J once and solves ``H X = E`` only for the 3 columns of each chosen vertex
    (in batches), never forming the inverse. Covariance of the gauge vertex is zero.

    Parameters
    ----------
    graph : PoseGraph, usually at an optimum (``graph.with_poses(result.poses)``).
    vertices : (k,) int vertex indices.
    cfg : OptimizerConfig, for the gauge, the kernel weights and the linear solver (default config
        when None).
    batch : vertices per multi-right-hand-side solve.

    Returns
    -------
    (k, 3, 3) float64 covariances in (x, y, theta), m^2 / rad^2.
    """
    v = np.asarray(vertices, dtype=np.int64).reshape(-1)
    if v.size and (v.min() < 0 or v.max() >= graph.n_vertices):
        raise ValueError(f"vertices must be in [0, {graph.n_vertices})")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    prob = _Problem(graph, cfg or OptimizerConfig())
    out = np.zeros((v.size, 3, 3))
    if prob.system is None:
        return out
    _, w, _ = prob.evaluate(graph.poses)
    data, _ = prob.normal_equations(graph.poses, w)
    if not prob.chol.factor(prob.system.matrix(data)):
        raise ValueError("graph: the information matrix is singular at these poses")
    pos = prob.system.pos[v]
    free = np.flatnonzero(pos >= 0)
    for s in range(0, free.size, batch):
        sel = free[s : s + batch]
        cols = (3 * pos[sel][:, None] + np.arange(3)).ravel()
        rhs = np.zeros((prob.system.size, cols.size))
        rhs[cols, np.arange(cols.size)] = 1.0
        x = prob.chol.solve(rhs)
        out[sel] = x[cols].reshape(sel.size, 3, sel.size, 3)[np.arange(sel.size), :, np.arange(sel.size), :]
    return 0.5 * (out + out.transpose(0, 2, 1))


def align_positions(estimate: ArrayLike, truth: ArrayLike) -> F64:
    """Rigidly align positions (n, 2+) onto ``truth`` (least squares, Kabsch/Umeyama without scale).

    Returns the aligned estimate positions, shape (n, 2).
    """
    p = np.asarray(estimate, dtype=np.float64)[:, :2]
    q = np.asarray(truth, dtype=np.float64)[:, :2]
    if p.shape != q.shape or p.shape[0] < 2:
        raise ValueError(f"estimate and truth must have the same shape (n >= 2, 2+), got {p.shape} and {q.shape}")
    mp, mq = p.mean(0), q.mean(0)
    u, _, vt = np.linalg.svd((q - mq).T @ (p - mp))
    d = np.sign(np.linalg.det(u @ vt))
    r = u @ np.diag([1.0, d]) @ vt
    return np.asarray((p - mp) @ r.T + mq, dtype=np.float64)


def aligned_position_rmse(estimate: ArrayLike, truth: ArrayLike) -> float:
    """Position RMSE (m) after rigid SE(2) alignment of ``estimate`` onto ``truth``."""
    a = align_positions(estimate, truth)
    q = np.asarray(truth, dtype=np.float64)[:, :2]
    return float(np.sqrt(np.mean(np.sum((a - q) ** 2, axis=1))))
