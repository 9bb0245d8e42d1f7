"""Sparse maximum-likelihood optimization of 2D pose graphs (Gauss-Newton and Levenberg-Marquardt).

Convention (g2o ``EdgeSE2`` [1]_): an edge k from vertex i to vertex j carries a measurement
``Z_k = [dx, dy, dtheta]``, the pose of j in the frame of i, and a 3x3 information matrix
``Omega_k`` in the order (x, y, theta). Its error is

    e_k = t2v(Z_k^-1 X_i^-1 X_j),   angle wrapped to [-pi, pi),

and ``chi2 = sum_k e_k^T Omega_k e_k``. Poses are updated additively in (x, y, theta), like g2o's
``VertexSE2``. One vertex (the gauge, vertex 0 by default) is held fixed.

Robust kernels (:mod:`slamreplay.algorithms.common.robust`) act through IRLS weights ``w_k`` on ``Omega_k``;
by default Dynamic Covariance Scaling [2]_ on loop closures (edges with ``|i - j| != 1``) only, in
two stages: (1) DCS with Phi graduated from the largest initial loop-closure chi2 (plain least
squares) down to 1 [3]_, so a poor start does not down-weight good closures; (2) closures whose
chi2 at that solution fails a chi-square gate (3 dof, p = 0.999) are dropped and the rest is
re-solved without a kernel, warm-started; a dropped closure whose innovation (residual against
its covariance plus the prediction's, a family-wise gate) fits the re-solved graph is re-admitted
if the re-solve that includes it keeps it within the gate. On a clean graph this ends at the plain
least-squares optimum with nothing rejected. ``chi2`` values reported are the plain, unweighted
sum above over the kept edges, so they compare with the literature.

References
----------
.. [1] R. Kümmerle, G. Grisetti, H. Strasdat, K. Konolige, W. Burgard, "g2o: A general framework
   for graph optimization", ICRA 2011.
.. [2] P. Agarwal, G. D. Tipaldi, L. Spinello, C. Stachniss, W. Burgard, "Robust map optimization
   using dynamic covariance scaling", ICRA 2013.
.. [3] H. Yang, P. Antonante, V. Tzoumas, L. Carlone, "Graduated non-convexity for robust spatial
   perception", RA-L 2020.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.stats import chi2 as chi2_distribution

from slamreplay.algorithms.common.robust import DEFAULT_PARAMETER, Kernel, weights_and_cost
from slamreplay.algorithms.common.se2 import wrap_angle
from slamreplay.algorithms.common.sparse_cholesky import Backend, BlockSystem, SparseCholesky

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


READMIT_ROUNDS = 3  # re-admission rounds at most after the plain re-solve
LM_DOWN, LM_UP = 0.1, 10.0  # damping factors; measured fewer iterations than Nielsen's rule here
CHORD_SLOW = 0.25  # a chord step whose decrease exceeds this fraction of the previous one: next step full


class Status(enum.Enum):
    """Outcome of an optimization; never an exception."""

    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    DIVERGED = "diverged"


def _frozen(a: ArrayLike, dtype: type, name: str) -> NDArray[Any]:
    out: NDArray[Any] = np.array(a, dtype=dtype, copy=True)
    if dtype is np.float64 and not np.all(np.isfinite(out)):
        raise ValueError(f"{name} must be finite")
    out.setflags(write=False)
    return out


def _checked_edges(i: ArrayLike, j: ArrayLike, z: ArrayLike, info: ArrayLike,
                   n: int) -> tuple[I64, I64, F64, F64]:
    """Read-only copies of edges between n vertices, validated (the incremental mode checks each update's)."""
    ii = _frozen(i, np.int64, "i")
    jj = _frozen(j, np.int64, "j")
    m = ii.shape[0] if ii.ndim == 1 else -1
    if ii.ndim != 1 or jj.shape != ii.shape:
        raise ValueError(f"i and j must have the same shape (m,), got {ii.shape} and {jj.shape}")
    if m and (min(ii.min(), jj.min()) < 0 or max(ii.max(), jj.max()) >= n):
        raise ValueError(f"i, j: vertex index out of range [0, {n})")
    if np.any(ii == jj):
        raise ValueError(f"i, j: self-loop edge at index {int(np.flatnonzero(ii == jj)[0])}")
    zz = _frozen(z, np.float64, "measurements")
    if zz.shape != (m, 3):
        raise ValueError(f"measurements must have shape ({m}, 3), got {zz.shape}")
    f = _frozen(info, np.float64, "information")
    if f.shape != (m, 3, 3):
        raise ValueError(f"information must have shape ({m}, 3, 3), got {f.shape}")
    # np.isclose's test, written out (a third of its time)
    f_t = f.transpose(0, 2, 1)
    bad = ~np.all(np.abs(f - f_t) <= 1e-12 + 1e-9 * np.abs(f_t), axis=(1, 2))
    if m:
        # Sylvester's criterion (leading minors > 0) in closed form, 5x faster than eigvalsh on a few
        # edges; eigvalsh decides the edges it flags, so rounding in the minors cannot reject an SPD matrix
        a, b, c, d, e, g = f[:, 0, 0], f[:, 1, 1], f[:, 2, 2], f[:, 0, 1], f[:, 1, 2], f[:, 0, 2]
        minor2 = a * b - d * d
        det = a * (b * c - e * e) - d * (d * c - e * g) + g * (d * e - b * g)
        maybe = ~((a > 0.0) & (minor2 > 0.0) & (det > 0.0))
        if np.any(maybe):
            bad[maybe] |= np.linalg.eigvalsh(f[maybe])[:, 0] <= 0.0
    if np.any(bad):
        raise ValueError(f"information[{int(np.flatnonzero(bad)[0])}] is not symmetric positive definite")
    return ii, jj, zz, f


@dataclass(frozen=True, slots=True, eq=False)
class PoseGraph:
    """A 2D pose graph; arrays are copied and made read-only.

    Attributes
    ----------
    poses : (n, 3) float64
        Current estimate ``[x, y, theta]`` of each vertex in the world frame (m, m, rad).
    i, j : (m,) int64
        Edge endpoints, vertex indices in ``[0, n)``, ``i != j``.
    measurements : (m, 3) float64
        Pose of j in the frame of i, ``[dx, dy, dtheta]``.
    information : (m, 3, 3) float64
        Symmetric positive-definite information matrices, order (x, y, theta).
    """

    poses: F64
    i: I64
    j: I64
    measurements: F64
    information: F64

    def __post_init__(self) -> None:
        poses = _frozen(self.poses, np.float64, "poses")
        if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape[0] < 1:
            raise ValueError(f"poses must have shape (n, 3) with n >= 1, got {poses.shape}")
        i, j, z, info = _checked_edges(self.i, self.j, self.measurements, self.information, poses.shape[0])
        for name, value in (("poses", poses), ("i", i), ("j", j), ("measurements", z), ("information", info)):
            object.__setattr__(self, name, value)

    @property
    def n_vertices(self) -> int:
        """Number of vertices n."""
        return int(self.poses.shape[0])

    @property
    def n_edges(self) -> int:
        """Number of edges m."""
        return int(self.i.shape[0])

    @classmethod
    def _trusted(cls, poses: F64, i: I64, j: I64, measurements: F64, information: F64) -> PoseGraph:
        """Build without validation, from arrays already checked (incremental use); not copied."""
        g = object.__new__(cls)
        for name, value in (("poses", poses), ("i", i), ("j", j), ("measurements", measurements),
                            ("information", information)):
            object.__setattr__(g, name, value)
        return g

    def with_poses(self, poses: ArrayLike) -> PoseGraph:
        """The same graph with another estimate (n, 3)."""
        p = np.asarray(poses, dtype=np.float64)
        if p.shape != self.poses.shape:
            raise ValueError(f"poses must have shape {self.poses.shape}, got {p.shape}")
        return PoseGraph(p, self.i, self.j, self.measurements, self.information)


@dataclass(frozen=True, slots=True)
class OptimizerConfig:
    """Settings of :func:`optimize`.

    Attributes
    ----------
    method : "gn" (Gauss-Newton) or "lm" (Levenberg-Marquardt with Marquardt's diagonal scaling;
        damping x0.1 after a step whose gain ratio exceeds 0.25, x10 after a rejected step).
    max_iterations : maximum number of linearizations.
    rel_tol : stop when the relative decrease of the robust cost in one iteration is in [0, rel_tol).
    step_tol : stop when the largest step component (m or rad) is below this.
    kernel : robust kernel; ``kernel_parameter`` None means the kernel's default (Phi = 1 for DCS).
    robust_all_edges : apply the kernel to sequential edges (|i - j| == 1) as well.
    gauge : index of the vertex held fixed, or a tuple of indices to hold several fixed.
    lm_lambda : initial LM damping, relative to diag(H).
    divergence_ratio : DIVERGED when the cost exceeds this multiple of the initial cost.
    linear_solver : "auto" (CHOLMOD if scikit-sparse or CVXOPT imports, else QDLDL, a core dependency,
        else SuperLU), "cholmod", "qdldl", "superlu".
    graduated : DCS only: start Phi at the largest loop-closure chi2 of the initial guess (no edge
        down-weighted, plain least squares) and divide it by ``graduated_factor`` per iteration
        down to the target Phi (graduated non-convexity), so a poor start does not down-weight
        good loop closures.
    graduated_factor : Phi shrink factor per iteration, in (0, 1).
    inlier_gate : with a kernel, a second stage: robust-set edges whose chi2 at the robust
        solution exceeds the chi-square (3 dof) quantile of this probability are rejected, and
        the rest is re-solved by plain least squares, warm-started. None: robust solve only.
    chord_tol : Gauss-Newton only: after a step that lowered the cost by a relative amount below
        this, the next step solves the new gradient with the last factorization (a chord, or
        simplified Newton, step: no assembly of H, no numeric factorization); a chord step that
        does not lower the cost is replaced by a full step. Near the optimum H barely changes, so
        the iteration still converges to the same optimum under the same ``rel_tol`` test
        (measured: docs/posegraph.md). 0: a full step every iteration.
    """

    method: str = "gn"
    max_iterations: int = 100
    rel_tol: float = 1e-6
    step_tol: float = 1e-9
    kernel: Kernel = Kernel.DCS
    kernel_parameter: float | None = None
    robust_all_edges: bool = False
    gauge: int | tuple[int, ...] = 0
    lm_lambda: float = 1e-5
    divergence_ratio: float = 1e6
    linear_solver: Backend = "auto"
    graduated: bool = True
    graduated_factor: float = 0.1
    inlier_gate: float | None = 0.999
    chord_tol: float = 0.1

    def __post_init__(self) -> None:
        if self.method not in ("gn", "lm"):
            raise ValueError(f"method must be 'gn' or 'lm', got {self.method!r}")
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {self.max_iterations}")
        for name in ("rel_tol", "step_tol", "lm_lambda"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not isinstance(self.kernel, Kernel):
            raise ValueError(f"kernel must be a Kernel, got {self.kernel!r}")
        if self.kernel_parameter is not None and not self.kernel_parameter > 0.0:
            raise ValueError(f"kernel_parameter must be > 0, got {self.kernel_parameter}")
        if not self.divergence_ratio > 1.0:
            raise ValueError(f"divergence_ratio must be > 1, got {self.divergence_ratio}")
        if self.linear_solver not in ("auto", "cholmod", "qdldl", "superlu"):
            raise ValueError(f"linear_solver must be auto, cholmod, qdldl or superlu, got {self.linear_solver!r}")
        if not 0.0 < self.graduated_factor < 1.0:
            raise ValueError(f"graduated_factor must be in (0, 1), got {self.graduated_factor}")
        if not 0.0 <= self.chord_tol < 1.0:
            raise ValueError(f"chord_tol must be in [0, 1), got {self.chord_tol}")
        if self.inlier_gate is not None and not 0.0 < self.inlier_gate < 1.0:
            raise ValueError(f"inlier_gate must be in (0, 1) or None, got {self.inlier_gate}")


@dataclass(frozen=True, slots=True, eq=False)
class OptimizationResult:
    """Result of :func:`optimize`.

    Attributes
    ----------
    poses : (n, 3) the lowest-cost estimate reached (world frame, gauge unchanged).
    status : CONVERGED, MAX_ITERATIONS or DIVERGED (of the last stage run).
    iterations : number of linearizations (GN steps; LM outer iterations), both stages.
    chi2_initial : plain g2o chi2 of all edges at the initial poses.
    chi2_final : plain g2o chi2 at the returned poses over the kept edges (``inliers``); all edges
        when ``edges_rejected`` is 0.
    chi2_history : (iterations + 1,) plain chi2 of each accepted iterate, initial first, over the
        edges in use (all in the robust stage, the kept ones in the re-solve).
    cost_history : (iterations + 1,) objective of the same iterates (robust cost, then plain chi2).
    edge_chi2 : (m,) per-edge chi2 at the returned poses (rejected edges included).
    weights : (m,) IRLS weights at the returned poses (1 where no kernel applies, 0 when rejected).
    n_factorizations : sparse Cholesky factorizations done.
    linear_solver : "cholmod", "qdldl" or "superlu".
    inliers : (m,) bool, False for the edges the inlier gate rejected.
    edges_rejected : number of rejected edges.
    """

    poses: F64
    status: Status
    iterations: int
    chi2_initial: float
    chi2_final: float
    chi2_history: F64
    cost_history: F64
    edge_chi2: F64
    weights: F64
    n_factorizations: int
    linear_solver: str
    lm_lambda: float = field(default=0.0)
    inliers: NDArray[np.bool_] = field(default_factory=lambda: np.ones(0, dtype=bool))
    edges_rejected: int = 0


def edge_errors(graph: PoseGraph, poses: ArrayLike | None = None) -> F64:
    """g2o EdgeSE2 errors ``e_k = t2v(Z_k^-1 X_i^-1 X_j)``, shape (m, 3), angle wrapped."""
    p = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    return linearize(p, graph.i, graph.j, graph.measurements, jacobians=False)[0].T


def chi2(graph: PoseGraph, poses: ArrayLike | None = None) -> float:
    """Plain chi2 ``sum_k e_k^T Omega_k e_k`` at ``poses`` (default: the graph's estimate)."""
    e = edge_errors(graph, poses)
    return float(np.einsum("mi,mij,mj->", e, graph.information, e))


def linearize(poses: F64, i: I64, j: I64, z: F64, jacobians: bool = True) -> tuple[F64, F64, F64]:
    """Errors and analytic Jacobians of g2o EdgeSE2 edges w.r.t. additive (x, y, theta) updates.

    Arrays are edge-last ("structure of arrays"), which keeps the batched 3x3 algebra vectorized.

    Returns
    -------
    e : (3, m) errors.
    ji, jj : (3, 3, m) ``de/dX_i`` and ``de/dX_j`` (empty arrays when ``jacobians`` is False).
    """
    pi, pj = poses[i], poses[j]
    dx, dy = pj[:, 0] - pi[:, 0], pj[:, 1] - pi[:, 1]
    a = pi[:, 2] + z[:, 2]
    c, s = np.cos(a), np.sin(a)
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    e = np.empty((3, i.size))
    # e_t = R(theta_z)^T (R(theta_i)^T (t_j - t_i) - t_z) = A (t_j - t_i) - R(theta_z)^T t_z
    e[0] = c * dx + s * dy - (cz * z[:, 0] + sz * z[:, 1])
    e[1] = -s * dx + c * dy - (-sz * z[:, 0] + cz * z[:, 1])
    e[2] = wrap_angle(pj[:, 2] - pi[:, 2] - z[:, 2])
    if not jacobians:
        return e, np.empty((3, 3, 0)), np.empty((3, 3, 0))
    jj = np.zeros((3, 3, i.size))
    jj[0, 0], jj[0, 1], jj[1, 0], jj[1, 1], jj[2, 2] = c, s, -s, c, 1.0
    ji = -jj
    ji[0, 2] = c * dy - s * dx  # d e_t / d theta_i = A [dy, -dx]
    ji[1, 2] = -s * dy - c * dx
    return e, ji, jj


def _edge_gradients(e: F64, c: F64, s: F64, u: F64, wf: tuple[F64, ...]) -> F64:
    """Per edge ``J_i^T W e`` and ``J_j^T W e`` (2, 3, m), from the errors, the Jacobians' parts (``cos``,
    ``sin``, ``u``: ``_Problem._errors``) and the weighted information's entries (w00, w01, w02, w11, w12, w22)."""
    w00, w01, w02, w11, w12, w22 = wf
    we0 = w00 * e[0] + w01 * e[1] + w02 * e[2]
    we1 = w01 * e[0] + w11 * e[1] + w12 * e[2]
    we2 = w02 * e[0] + w12 * e[1] + w22 * e[2]
    grad = np.empty((2, 3, e.shape[1]))
    grad[1, 0], grad[1, 1], grad[1, 2] = c * we0 - s * we1, s * we0 + c * we1, we2
    np.negative(grad[1], out=grad[0])
    grad[0, 2] += u[0] * we0 + u[1] * we1
    return grad


class _Problem:
    """A graph with its fixed structure: the block system, the factorization, the kernel mask."""

    def __init__(self, graph: PoseGraph, cfg: OptimizerConfig, order: I64 | None = None,
                 check_connected: bool = True, robust: NDArray[np.bool_] | None = None) -> None:
        n = graph.n_vertices
        gauge = np.atleast_1d(np.asarray(cfg.gauge, dtype=np.int64))
        if gauge.size == 0 or gauge.min() < 0 or gauge.max() >= n:
            raise ValueError(f"gauge must be vertex indices in [0, {n}), got {cfg.gauge}")
        if n > 1 and check_connected:
            adj = coo_matrix((np.ones(graph.n_edges), (graph.i, graph.j)), shape=(n, n))
            k = connected_components(adj, directed=False)[0]
            if k != 1:
                raise ValueError(f"graph has {k} connected components; with one gauge vertex it must be connected")
        self.graph = graph
        self.cfg = cfg
        if robust is not None:
            self.robust = np.array(robust, dtype=bool).reshape(-1)
            if self.robust.shape != (graph.n_edges,):
                raise ValueError(f"robust must have shape ({graph.n_edges},), got {self.robust.shape}")
        elif cfg.robust_all_edges:
            self.robust = np.ones(graph.n_edges, dtype=bool)
        else:
            self.robust = np.abs(graph.i - graph.j) != 1
        self.kernel = cfg.kernel
        self.kparam = cfg.kernel_parameter or DEFAULT_PARAMETER[cfg.kernel]
        self.info = np.ascontiguousarray(graph.information.transpose(1, 2, 0))  # (3, 3, m)
        self.fixed = tuple(int(v) for v in np.unique(gauge))
        self.chol = SparseCholesky(cfg.linear_solver)
        if order is None and self.chol.orders_itself:
            order = np.arange(n - len(self.fixed), dtype=np.int64)
        self.system = (BlockSystem(n, graph.i, graph.j, self.fixed, order=order, lower=self.chol.wants_lower,
                                   upper=self.chol.wants_upper)
                       if n > len(self.fixed) else None)
        self._lin: tuple[F64, F64, F64, F64, F64] | None = None  # poses, e, cos, sin, u of the last evaluate
        z = graph.measurements
        cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
        self._zt = np.ascontiguousarray(z[:, 2])
        self._rz = np.stack([cz * z[:, 0] + sz * z[:, 1], -sz * z[:, 0] + cz * z[:, 1]])  # R(theta_z)^T t_z

    def _errors(self, poses: F64) -> tuple[F64, F64, F64, F64]:
        """Errors (3, m) and what the Jacobians need (cos, sin, u): kept for ``normal_equations`` at the same poses."""
        if self._lin is not None and self._lin[0] is poses:
            return self._lin[1:]
        g = self.graph
        pi, pj = poses.take(g.i, axis=0).T, poses.take(g.j, axis=0).T  # take: 4x faster than poses[g.i]
        dx, dy = pj[0] - pi[0], pj[1] - pi[1]
        a = pi[2] + self._zt
        c, s = np.cos(a), np.sin(a)
        e = np.empty((3, g.n_edges))
        e[0] = c * dx + s * dy - self._rz[0]
        e[1] = c * dy - s * dx - self._rz[1]
        e[2] = wrap_angle(pj[2] - pi[2] - self._zt)
        u = np.empty((2, g.n_edges))
        u[0] = c * dy - s * dx  # d e_t / d theta_i
        u[1] = -(s * dy + c * dx)
        self._lin = (poses, e, c, s, u)
        return e, c, s, u

    def evaluate(self, poses: F64) -> tuple[F64, F64, float]:
        """Per-edge chi2, IRLS weights and the total robust cost."""
        e = self._errors(poses)[0]
        f = self.info
        c2 = (f[0, 0] * e[0] * e[0] + f[1, 1] * e[1] * e[1] + f[2, 2] * e[2] * e[2]
              + 2.0 * (f[0, 1] * e[0] * e[1] + f[0, 2] * e[0] * e[2] + f[1, 2] * e[1] * e[2]))
        return (c2, *self.reweight(c2))

    def reweight(self, c2: F64) -> tuple[F64, float]:
        """IRLS weights and robust cost of per-edge chi2 under the current kernel parameter."""
        w = np.ones_like(c2)
        cost = c2.copy()
        if self.kernel is not Kernel.NONE and np.any(self.robust):
            w[self.robust], cost[self.robust] = weights_and_cost(self.kernel, c2[self.robust], self.kparam)
        return w, float(cost.sum())

    def normal_equations(self, poses: F64, w: F64) -> tuple[F64, F64]:
        """CSC data of H = J^T W J and b = J^T W e (permuted order).

        The Jacobians are ``J_j = diag(R, 1)`` with ``R = [[c, s], [-s, c]]`` and ``J_i = -J_j + u e_3^T``
        (:func:`linearize`), so with ``M = J_j^T W J_j`` and ``v = J_j^T W u``: ``H_jj = M``,
        ``H_ij = -M + e_3 v^T``, ``H_ii = M - e_3 v^T - v e_3^T + (u^T W u) e_3 e_3^T``, written out
        per entry: an einsum chain over (3, 3, m) arrays took 4x longer.
        """
        assert self.system is not None
        e, c, s, u = self._errors(poses)
        f = self.info
        w00, w01, w02, w11, w12, w22 = (f[0, 0] * w, f[0, 1] * w, f[0, 2] * w, f[1, 1] * w, f[1, 2] * w, f[2, 2] * w)
        a00, a01, a10, a11 = w00 * c - w01 * s, w00 * s + w01 * c, w01 * c - w11 * s, w01 * s + w11 * c
        m00, m01, m11 = c * a00 - s * a10, c * a01 - s * a11, s * a01 + c * a11
        m02, m12 = c * w02 - s * w12, s * w02 + c * w12
        y0, y1, y2 = w00 * u[0] + w01 * u[1], w01 * u[0] + w11 * u[1], w02 * u[0] + w12 * u[1]
        v0, v1, v2 = c * y0 - s * y1, s * y0 + c * y1, y2
        suu = u[0] * y0 + u[1] * y1
        blocks = np.empty((3, 3, 3, self.graph.n_edges))
        hjj, hij, hii = blocks[2], blocks[1], blocks[0]
        hjj[0, 0], hjj[0, 1], hjj[0, 2], hjj[1, 1], hjj[1, 2], hjj[2, 2] = m00, m01, m02, m11, m12, w22
        hjj[1, 0], hjj[2, 0], hjj[2, 1] = m01, m02, m12
        np.negative(hjj, out=hij)
        hij[2, 0] += v0
        hij[2, 1] += v1
        hij[2, 2] += v2
        hii[:] = hjj
        hii[2, 0] -= v0
        hii[2, 1] -= v1
        hii[0, 2] -= v0
        hii[1, 2] -= v1
        hii[2, 2] += suu - 2.0 * v2
        grad = _edge_gradients(e, c, s, u, (w00, w01, w02, w11, w12, w22))
        return self.system.assemble(blocks, grad)

    def gradient(self, poses: F64, w: F64) -> F64:
        """b = J^T W e alone (permuted order), for a step with an earlier factorization."""
        assert self.system is not None
        e, c, s, u = self._errors(poses)
        f = self.info
        wf = (f[0, 0] * w, f[0, 1] * w, f[0, 2] * w, f[1, 1] * w, f[1, 2] * w, f[2, 2] * w)
        return self.system.assemble_gradient(_edge_gradients(e, c, s, u, wf))

    def step(self, data: F64, b: F64, damping: F64 | None) -> F64 | None:
        """Solve (H + diag(damping)) dx = -b; None when the factorization fails."""
        assert self.system is not None
        if damping is not None:
            data = data.copy()
            data[self.system.diag_slots] += damping
        if not self.chol.factor(self.system.matrix(data)):
            return None
        try:
            return -self.chol.solve(b)
        except np.linalg.LinAlgError:  # a zero pivot only the solve could tell (QDLDL's re-factorization)
            return None

    def apply(self, poses: F64, dx: F64) -> F64:
        """Additive update of the free vertices, heading wrapped."""
        assert self.system is not None
        out = poses + self.system.scatter(dx, poses.shape[0])
        out[:, 2] = wrap_angle(out[:, 2])
        return out


def optimize(graph: PoseGraph, cfg: OptimizerConfig = OptimizerConfig(),
             robust: NDArray[np.bool_] | None = None) -> OptimizationResult:
    """Minimize the (robust) chi2 of a pose graph from its current estimate.

    Parameters
    ----------
    graph : PoseGraph
        Must be connected. ``graph.poses`` is the initial guess (see
        :mod:`slamreplay.algorithms.common.posegraph_init` for odometry and chordal initializations).
    cfg : OptimizerConfig
    robust : (m,) bool, optional
        The edges the kernel (and the inlier gate) applies to; None: the config's rule (loop
        closures ``|i - j| != 1``, or every edge with ``robust_all_edges``).

    Returns
    -------
    OptimizationResult
        ``status`` tells whether the relative-cost or step-size test was met (CONVERGED), the
        iteration budget ran out (MAX_ITERATIONS), or the cost blew up / the system became
        singular (DIVERGED). The lowest-cost estimate is returned in every case.

    References
    ----------
    .. [1] Kümmerle et al., ICRA 2011 (g2o), sec. III; Agarwal et al., ICRA 2013 (DCS).
    """
    prob = _Problem(graph, cfg, robust=robust)
    is_robust = cfg.kernel is not Kernel.NONE and bool(np.any(prob.robust))
    phi0 = None
    if is_robust and cfg.graduated and cfg.kernel is Kernel.DCS:
        c2 = prob.evaluate(graph.poses)[0]
        phi0 = float(c2[prob.robust].max())
    res = _run(prob, graph.poses.copy(), cfg, phi0)
    if not is_robust or cfg.inlier_gate is None or res.status is Status.DIVERGED or prob.system is None:
        return res
    gate = float(chi2_distribution.ppf(cfg.inlier_gate, 3))
    # family-wise gate (Bonferroni over the tested edges) for edges once rejected
    wide = float(chi2_distribution.isf((1.0 - cfg.inlier_gate) / int(prob.robust.sum()), 3))
    keep = _inliers(graph, prob.robust, res.edge_chi2, gate)
    r2, sub = _plain(prob, graph, keep, res.poses, cfg)
    parts = [res, r2]
    c2 = prob.evaluate(parts[-1].poses)[0] if not keep.all() else parts[-1].edge_chi2
    for _ in range(READMIT_ROUNDS):
        if keep.all() or parts[-1].status is Status.DIVERGED:
            break
        # A good closure the robust stage stretched past the gate is consistent with the graph
        # without it (its residual against its own plus the prediction's covariance); re-admit
        # such edges if the re-solve keeps every re-admitted edge within the gate.
        out = np.flatnonzero(~keep)
        back = out[_innovation_chi2(sub, graph, out, parts[-1].poses) <= wide]
        if back.size == 0:
            break
        trial = keep.copy()
        trial[back] = True
        r, s2 = _plain(prob, graph, trial, parts[-1].poses, cfg)
        c2t = prob.evaluate(r.poses)[0]
        if not (r.status is Status.CONVERGED and np.all(c2t[back] <= gate)
                and np.all(c2t[trial & prob.robust] <= wide)):
            break
        parts.append(r)
        keep, c2, sub = trial, c2t, s2
    last = parts[-1]
    return OptimizationResult(
        poses=last.poses, status=last.status, iterations=sum(r.iterations for r in parts),
        chi2_initial=res.chi2_initial, chi2_final=float(c2[keep].sum()),
        chi2_history=np.concatenate([res.chi2_history, *(r.chi2_history[1:] for r in parts[1:])]),
        cost_history=np.concatenate([res.cost_history, *(r.cost_history[1:] for r in parts[1:])]),
        edge_chi2=c2, weights=keep.astype(np.float64), n_factorizations=sum(r.n_factorizations for r in parts),
        linear_solver=last.linear_solver, lm_lambda=last.lm_lambda, inliers=keep,
        edges_rejected=int(keep.size - keep.sum()),
    )


def _plain(prob: _Problem, graph: PoseGraph, keep: NDArray[np.bool_], poses: F64,
           cfg: OptimizerConfig) -> tuple[OptimizationResult, _Problem]:
    """Plain least squares on the kept edges from ``poses``; fewer edges get their own, sparser structure."""
    if keep.all():
        prob.kernel = Kernel.NONE
        sub = prob
    else:
        g = PoseGraph._trusted(graph.poses, graph.i[keep], graph.j[keep], graph.measurements[keep],
                               graph.information[keep])
        sub = _Problem(g, replace(cfg, kernel=Kernel.NONE), check_connected=False)
    return _run(sub, poses.copy(), cfg), sub


def _innovation_chi2(prob: _Problem, graph: PoseGraph, edges: I64, poses: F64, batch: int = 32) -> F64:
    """``e^T (Omega^-1 + J H^-1 J^T)^-1 e`` of edges absent from ``prob``, at ``poses``."""
    assert prob.system is not None
    e, ji, jj = linearize(poses, graph.i[edges], graph.j[edges], graph.measurements[edges])
    _, w, _ = prob.evaluate(poses)
    if not prob.chol.factor(prob.system.matrix(prob.normal_equations(poses, w)[0])):
        return np.full(edges.size, np.inf)
    pos = prob.system.pos
    cov = np.linalg.inv(graph.information[edges])  # (k, 3, 3)
    out = np.empty(edges.size)
    d = np.arange(3)
    for s in range(0, edges.size, batch):
        t = np.arange(s, min(s + batch, edges.size))
        rhs = np.zeros((prob.system.size, 3 * t.size))
        ends = [(pos[graph.i[edges[t]]], ji[:, :, t]), (pos[graph.j[edges[t]]], jj[:, :, t])]
        for p, jac in ends:  # column 3 k + c holds row c of the edge Jacobian (its transpose)
            ok = np.flatnonzero(p >= 0)
            rows = 3 * p[ok][:, None, None] + d[None, None, :]  # (k, c, d)
            cols = 3 * ok[:, None, None] + d[None, :, None]
            rhs[rows, cols] = jac[:, :, ok].transpose(2, 0, 1)
        x = prob.chol.solve(rhs).reshape(prob.system.size, t.size, 3)
        m = np.zeros((t.size, 3, 3))
        for p, jac in ends:
            ok = np.flatnonzero(p >= 0)
            xb = x[3 * p[ok][:, None] + d, ok[:, None], :]  # (k, d, c')
            m[ok] += np.einsum("cdk,kde->kce", jac[:, :, ok], xb)
        r = e[:, t].T
        out[t] = np.einsum("ki,ki->k", r, np.linalg.solve(cov[t] + m, r[:, :, None])[:, :, 0])
    return out


def _inliers(graph: PoseGraph, robust: NDArray[np.bool_], c2: F64, gate: float) -> NDArray[np.bool_]:
    """Edges passing the chi2 gate; rejected edges needed to keep the graph connected are kept."""
    keep = ~robust | (c2 <= gate)
    n = graph.n_vertices
    if keep.all() or n < 2:
        return keep
    adj = coo_matrix((np.ones(int(keep.sum())), (graph.i[keep], graph.j[keep])), shape=(n, n))
    k, label = connected_components(adj, directed=False)
    if k == 1:
        return keep
    root = list(range(k))

    def find(a: int) -> int:
        while root[a] != a:
            root[a] = root[root[a]]
            a = root[a]
        return a

    out = np.flatnonzero(~keep)
    for e in out[np.argsort(c2[out], kind="stable")]:  # best-fitting bridges first
        a, b = find(int(label[graph.i[e]])), find(int(label[graph.j[e]]))
        if a != b:
            root[a] = b
            keep[e] = True
    return keep


def _run(prob: _Problem, poses: F64, cfg: OptimizerConfig, phi0: float | None = None) -> OptimizationResult:
    """Iterate from ``poses``; with ``phi0``, the kernel parameter starts there and shrinks to its target."""
    target = prob.kparam
    graduating = phi0 is not None and phi0 > target
    if graduating:
        prob.kparam = float(phi0)  # type: ignore[arg-type]
    c2, w, cost = prob.evaluate(poses)
    chi2_hist, cost_hist = [float(c2.sum())], [cost]
    best = (cost, poses, c2, w)
    status, iters, nfact = Status.MAX_ITERATIONS, 0, 0
    lam = cfg.lm_lambda
    if prob.system is None or cost == 0.0:
        status = Status.CONVERGED
    rel_prev = np.inf  # relative decrease of the last step (outside graduation)
    slow = False  # the last chord step contracted slowly: take a full step next
    dx: F64 | None
    while status is Status.MAX_ITERATIONS and iters < cfg.max_iterations:
        iters += 1
        chord = cfg.method == "gn" and nfact > 0 and 0.0 <= rel_prev < cfg.chord_tol and not slow
        slow = False
        if chord:  # near convergence: the last factorization, the new gradient (a solve, no factorization)
            dx = -prob.chol.solve(prob.gradient(poses, w))
            new = prob.apply(poses, dx)
            c2n, wn, costn = prob.evaluate(new)
            chord = bool(np.isfinite(costn) and costn <= cost)  # else a full step from the same poses
        if chord:
            assert dx is not None
        elif cfg.method == "gn":
            data, b = prob.normal_equations(poses, w)
            dx = prob.step(data, b, None)
            nfact += 1
            if dx is None:
                status = Status.DIVERGED
                break
            new = prob.apply(poses, dx)
            c2n, wn, costn = prob.evaluate(new)
        else:
            data, b = prob.normal_equations(poses, w)
            diag = np.maximum(data[prob.system.diag_slots], 1e-12 * max(1.0, float(data.max())))  # type: ignore[union-attr]
            while True:
                dx = prob.step(data, b, lam * diag)
                nfact += 1
                if dx is not None:
                    new = prob.apply(poses, dx)
                    c2n, wn, costn = prob.evaluate(new)
                    # einsum, not BLAS dot: threaded OpenBLAS took 8 ms for one 10^4 dot on a busy machine
                    pred = float(np.einsum("i,i->", dx, lam * diag * dx - b))
                    rho = (cost - costn) / pred if pred > 0.0 else -1.0
                    if np.isfinite(costn) and rho > 0.0:
                        lam = max(lam * LM_DOWN if rho > 0.25 else lam, 1e-15)
                        break
                lam *= LM_UP
                if lam > 1e16:  # no step decreases the cost: a minimum to machine precision
                    dx = None
                    break
            if dx is None:
                status = Status.CONVERGED
                break
        if not np.isfinite(costn):
            status = Status.DIVERGED
            break
        rel = (cost - costn) / cost if cost > 0.0 else 0.0
        poses, c2, w, cost = new, c2n, wn, costn
        chi2_hist.append(float(c2.sum()))
        cost_hist.append(cost)
        if graduating:  # costs under different parameters do not compare: restart the tests
            prob.kparam = max(target, prob.kparam * cfg.graduated_factor)
            graduating = prob.kparam > target
            w, cost = prob.reweight(c2)
            best = (cost, poses, c2, w)
            continue
        slow = chord and rel > CHORD_SLOW * rel_prev
        rel_prev = rel
        if cost < best[0]:
            best = (cost, poses, c2, w)
        if cost > cfg.divergence_ratio * cost_hist[0]:
            status = Status.DIVERGED
        elif (0.0 <= rel < cfg.rel_tol and not slow) or float(np.abs(dx).max(initial=0.0)) < cfg.step_tol:
            status = Status.CONVERGED
    prob.kparam = target
    _, poses, c2, w = best
    return OptimizationResult(
        poses=poses, status=status, iterations=iters, chi2_initial=chi2_hist[0], chi2_final=float(c2.sum()),
        chi2_history=np.array(chi2_hist), cost_history=np.array(cost_hist), edge_chi2=c2, weights=w,
        n_factorizations=nfact, linear_solver=prob.chol.backend, lm_lambda=lam,
        inliers=np.ones(c2.size, dtype=bool),
    )

