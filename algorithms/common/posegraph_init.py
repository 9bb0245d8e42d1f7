"""Initial guesses for 2D pose graphs: odometry composition and a linear (LAGO-style) chordal start.

Both walk a spanning tree rooted at the gauge vertex that prefers sequential edges
(``|i - j| == 1``, usually odometry), composed by pointer jumping so that no Python loop runs
over vertices.

References
----------
.. [1] L. Carlone, R. Aragues, J. A. Castellanos, B. Bona, "A fast and accurate approximation for
   planar pose graph optimization", IJRR 33(7), 2014 (LAGO), sec. 4: orientation regularization
   along a spanning tree, linear estimation of orientations, then of positions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

from slamreplay.algorithms.common.posegraph import PoseGraph
from slamreplay.algorithms.common.se2 import compose, inverse, wrap_angle
from slamreplay.algorithms.common.sparse_cholesky import Backend, BlockSystem, SparseCholesky

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def spanning_tree(
    graph: PoseGraph, root: int = 0, prefer_sequential: bool = True
) -> tuple[I64, I64, NDArray[np.bool_]]:
    """A spanning tree as (parent, edge, forward) per vertex.

    With ``prefer_sequential`` the tree is a minimum spanning tree that takes sequential edges
    (``|i - j| == 1``, odometry) before others; without it, a breadth-first tree from the root
    (fewest hops to every vertex, so the least accumulated drift along tree paths).

    ``parent[v]`` is v's parent (``root`` for the root), ``edge[v]`` the index of the tree edge
    joining them (-1 at the root), ``forward[v]`` True when that edge goes parent -> v.
    Raises ValueError when the graph is not connected.
    """
    n = graph.n_vertices
    if not 0 <= root < n:
        raise ValueError(f"root must be a vertex index in [0, {n}), got {root}")
    parent = np.full(n, root, dtype=np.int64)
    edge = np.full(n, -1, dtype=np.int64)
    fwd = np.ones(n, dtype=bool)
    if n == 1:
        return parent, edge, fwd
    i, j = graph.i, graph.j
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    weight = np.where(hi - lo == 1, 1.0, 2.0) if prefer_sequential else np.ones(i.size)
    key = lo * n + hi
    order = np.lexsort((np.arange(i.size), weight, key))  # per pair: lightest, then first in file
    first = order[np.r_[True, key[order][1:] != key[order][:-1]]]
    adj = coo_matrix((weight[first], (lo[first], hi[first])), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(adj) if prefer_sequential else adj
    _, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
    pred = np.asarray(pred, dtype=np.int64)
    reached = pred >= 0
    reached[root] = True
    if not np.all(reached):
        v0 = int(np.flatnonzero(~reached)[0])
        raise ValueError(f"graph is not connected: vertex {v0} is unreachable from vertex {root}")
    v = np.flatnonzero(np.arange(n) != root)
    p = pred[v]
    ukey = key[first]
    srt = np.argsort(ukey, kind="stable")
    k = first[srt[np.searchsorted(ukey[srt], np.minimum(p, v) * n + np.maximum(p, v))]]
    parent[v], edge[v], fwd[v] = p, k, i[k] == p
    return parent, edge, fwd


def _accumulate_poses(parent: I64, rel: F64, root: int) -> F64:
    """Poses of every vertex in the root frame from poses relative to the parent (pointer jumping)."""
    anc, t = parent.copy(), rel.copy()
    t[root] = 0.0
    while True:
        m = np.flatnonzero(anc != root)
        if m.size == 0:
            return t
        t[m] = compose(t[anc[m]], t[m])
        anc[m] = anc[anc[m]]


def _accumulate_angles(parent: I64, rel: F64, root: int) -> F64:
    """Unwrapped angle sums from the root along the tree (pointer jumping)."""
    anc, a = parent.copy(), rel.copy()
    a[root] = 0.0
    while True:
        m = np.flatnonzero(anc != root)
        if m.size == 0:
            return a
        a[m] = a[anc[m]] + a[m]
        anc[m] = anc[anc[m]]


def init_odometry(graph: PoseGraph, root: int = 0) -> F64:
    """Compose measurements along a spanning tree (sequential edges first) from ``graph.poses[root]``.

    Returns
    -------
    (n, 3) float64 poses; the root keeps its pose.
    """
    parent, edge, fwd = spanning_tree(graph, root)
    z = graph.measurements[np.maximum(edge, 0)]
    rel = np.where(fwd[:, None], z, inverse(z))
    poses = compose(graph.poses[root], _accumulate_poses(parent, rel, root))
    poses[root] = graph.poses[root]
    return poses


def init_chordal(graph: PoseGraph, root: int = 0, backend: Backend = "auto") -> F64:
    """Linear-angle (LAGO-style) initialization: orientations first, then positions [1]_.

    1. Tree orientations: unwrapped sums of the measured rotations along a breadth-first
       spanning tree from the root.
    2. Each edge's measured rotation is unwrapped by the multiple of 2 pi that makes it agree
       with the tree (LAGO's regularization), so the rotation problem becomes linear.
    3. Weighted linear least squares on the orientations, weights ``1 / Sigma_theta`` of each edge.
    4. With orientations fixed, the error is linear in the positions; a weighted linear least
       squares on them (conditional information ``Omega_tt``) gives the positions.

    Returns
    -------
    (n, 3) float64 poses; the root keeps its pose.
    """
    n = graph.n_vertices
    # Breadth-first tree: short tree paths keep the drift small where 2 pi ambiguities are resolved;
    # on MIT this reaches chi2 41.2 where the odometry tree (and odometry init) ends at 770.7.
    parent, edge, fwd = spanning_tree(graph, root, prefer_sequential=False)
    x0 = graph.poses[root]
    if n == 1:
        return graph.poses.copy()
    i, j, z, info = graph.i, graph.j, graph.measurements, graph.information
    dth = np.where(fwd, z[np.maximum(edge, 0), 2], -z[np.maximum(edge, 0), 2])
    th_tree = x0[2] + _accumulate_angles(parent, dth, root)
    delta = z[:, 2] + 2.0 * np.pi * np.round((th_tree[j] - th_tree[i] - z[:, 2]) / (2.0 * np.pi))
    cov = np.linalg.inv(info)
    w = 1.0 / cov[:, 2, 2]
    # orientations: r_k = th_j - th_i - delta_k, linearized at the tree solution (exact: linear)
    sys1 = BlockSystem(n, i, j, root, dim=1)
    blocks = (np.array([1.0, -1.0, -1.0, 1.0])[:, None] * w).reshape(4, 1, 1, -1)
    r = th_tree[j] - th_tree[i] - delta
    data, b = sys1.assemble(blocks, np.stack([-w * r, w * r])[:, None, :])
    chol = SparseCholesky(backend)
    if not chol.factor(sys1.matrix(data)):
        raise ValueError("graph: singular orientation system")
    th = th_tree + sys1.scatter(-chol.solve(b), n)[:, 0]
    # positions: e_t = A_k (t_j - t_i) - c_k with A_k = R(-(th_i + dth_k)); best c_k given e_theta
    a = th[i] + z[:, 2]
    ca, sa = np.cos(a), np.sin(a)
    amat = np.stack([np.stack([ca, sa], -1), np.stack([-sa, ca], -1)], -2)  # (m, 2, 2)
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    rz_t = np.stack([cz * z[:, 0] + sz * z[:, 1], -sz * z[:, 0] + cz * z[:, 1]], -1)
    e_th = wrap_angle(th[j] - th[i] - z[:, 2])
    om_tt = info[:, :2, :2]
    c = rz_t - np.linalg.solve(om_tt, (info[:, :2, 2] * e_th[:, None])[..., None])[..., 0]
    m_w = amat.transpose(0, 2, 1) @ om_tt @ amat  # world-frame information of t_j - t_i
    mt = m_w.transpose(1, 2, 0)
    blocks2 = np.stack([mt, -mt, -mt, mt])
    g = (amat.transpose(0, 2, 1) @ (om_tt @ (-c)[..., None]))[..., 0]  # J_j^T Omega r at t_j = t_i
    sys2 = BlockSystem(n, i, j, root, dim=2)
    data2, b2 = sys2.assemble(blocks2, np.stack([-g.T, g.T]))
    chol2 = SparseCholesky(backend)
    if not chol2.factor(sys2.matrix(data2)):
        raise ValueError("graph: singular position system")
    t = x0[:2] + sys2.scatter(-chol2.solve(b2), n)
    poses = np.column_stack([t, wrap_angle(th)])
    poses[root] = x0
    return poses
