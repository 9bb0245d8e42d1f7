"""Sparse maximum-likelihood optimization of 2D pose graphs (Gauss-Newton and Levenberg-Marquardt).

Convention (g2o ``EdgeSE2`` [1]_): an edge k from vertex i to vertex j carries a measurement
``Z_k = [dx, dy, dtheta]``, the pose of j in the frame of i, and a 3x3 information matrix
``Omega_k`` in the order (x, y, theta). Its error is

    e_k = t2v(Z_k^-1 X_i^-1 X_j),   angle wrapped to [-pi, pi),

and ``chi2 = sum_k e_k^T Omega_k e_k``. Poses are updated additively in (x, y, theta), like g2o's
``VertexSE2``. One vertex (the gauge, vertex 0 by default) is held fixed.

Robust kernels (:mod:`algorithms.common.robust`) act through IRLS weights ``w_k`` on ``Omega_k``;
by default Dynamic Covariance Scaling [2]_ on loop closures (edges with ``|i - j| != 1``) only.
``chi2`` values reported are always the plain, unweighted sum above, so they compare with the
literature; the robust objective is reported separately as ``cost``.

References
----------
.. [1] R. Kümmerle, G. Grisetti, H. Strasdat, K. Konolige, W. Burgard, "g2o: A general framework
   for graph optimization", ICRA 2011.
.. [2] P. Agarwal, G. D. Tipaldi, L. Spinello, C. Stachniss, W. Burgard, "Robust map optimization
   using dynamic covariance scaling", ICRA 2013.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from algorithms.common.robust import DEFAULT_PARAMETER, Kernel, weights_and_cost
from algorithms.common.se2 import wrap_angle
from algorithms.common.sparse_cholesky import Backend, BlockSystem, SparseCholesky

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


LM_DOWN, LM_UP = 0.1, 10.0  # damping factors; measured fewer iterations than Nielsen's rule here


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
        i = _frozen(self.i, np.int64, "i")
        j = _frozen(self.j, np.int64, "j")
        m = i.shape[0] if i.ndim == 1 else -1
        if i.ndim != 1 or j.shape != i.shape:
            raise ValueError(f"i and j must have the same shape (m,), got {i.shape} and {j.shape}")
        n = poses.shape[0]
        if m and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
            raise ValueError(f"i, j: vertex index out of range [0, {n})")
        if np.any(i == j):
            raise ValueError(f"i, j: self-loop edge at index {int(np.flatnonzero(i == j)[0])}")
        z = _frozen(self.measurements, np.float64, "measurements")
        if z.shape != (m, 3):
            raise ValueError(f"measurements must have shape ({m}, 3), got {z.shape}")
        info = _frozen(self.information, np.float64, "information")
        if info.shape != (m, 3, 3):
            raise ValueError(f"information must have shape ({m}, 3, 3), got {info.shape}")
        bad = ~np.all(np.isclose(info, info.transpose(0, 2, 1), rtol=1e-9, atol=1e-12), axis=(1, 2))
        if m:
            bad |= np.linalg.eigvalsh(info)[:, 0] <= 0.0
        if np.any(bad):
            raise ValueError(f"information[{int(np.flatnonzero(bad)[0])}] is not symmetric positive definite")
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
    linear_solver : "auto" (CHOLMOD if scikit-sparse imports, else SuperLU), "cholmod", "superlu".
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
        if self.linear_solver not in ("auto", "cholmod", "superlu"):
            raise ValueError(f"linear_solver must be auto, cholmod or superlu, got {self.linear_solver!r}")


@dataclass(frozen=True, slots=True, eq=False)
class OptimizationResult:
    """Result of :func:`optimize`.

    Attributes
    ----------
    poses : (n, 3) the lowest-cost estimate reached (world frame, gauge unchanged).
    status : CONVERGED, MAX_ITERATIONS or DIVERGED.
    iterations : number of linearizations (GN steps; LM outer iterations).
    chi2_initial, chi2_final : plain g2o chi2 at the initial and returned poses.
    chi2_history : (iterations + 1,) plain chi2 of each accepted iterate, initial first.
    cost_history : (iterations + 1,) robust cost of the same iterates.
    edge_chi2 : (m,) per-edge chi2 at the returned poses.
    weights : (m,) IRLS weights at the returned poses (1 where no kernel applies).
    n_factorizations : sparse Cholesky factorizations done.
    linear_solver : "cholmod" or "superlu".
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


class _Problem:
    """A graph with its fixed structure: the block system, the factorization, the kernel mask."""

    def __init__(self, graph: PoseGraph, cfg: OptimizerConfig, order: I64 | None = None,
                 check_connected: bool = True) -> None:
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
        self.robust = np.ones(graph.n_edges, dtype=bool) if cfg.robust_all_edges else np.abs(graph.i - graph.j) != 1
        self.kparam = cfg.kernel_parameter or DEFAULT_PARAMETER[cfg.kernel]
        self.info = np.ascontiguousarray(graph.information.transpose(1, 2, 0))  # (3, 3, m)
        self.fixed = tuple(int(v) for v in np.unique(gauge))
        self.system = BlockSystem(n, graph.i, graph.j, self.fixed, order=order) if n > len(self.fixed) else None
        self.chol = SparseCholesky(cfg.linear_solver)

    def evaluate(self, poses: F64) -> tuple[F64, F64, float]:
        """Per-edge chi2, IRLS weights and the total robust cost."""
        g = self.graph
        e = linearize(poses, g.i, g.j, g.measurements, jacobians=False)[0]
        c2 = np.einsum("im,ijm,jm->m", e, self.info, e)
        w = np.ones_like(c2)
        cost = c2.copy()
        if self.cfg.kernel is not Kernel.NONE and np.any(self.robust):
            w[self.robust], cost[self.robust] = weights_and_cost(self.cfg.kernel, c2[self.robust], self.kparam)
        return c2, w, float(cost.sum())

    def normal_equations(self, poses: F64, w: F64) -> tuple[F64, F64]:
        """CSC data of H = J^T W J and b = J^T W e (permuted order)."""
        assert self.system is not None
        g = self.graph
        e, ji, jj = linearize(poses, g.i, g.j, g.measurements)
        wm = self.info * w
        blocks = np.empty((4, 3, 3, g.n_edges))
        p = np.einsum("ikm,kjm->ijm", wm, jj)
        np.einsum("kim,kjm->ijm", ji, np.einsum("ikm,kjm->ijm", wm, ji), out=blocks[0])
        np.einsum("kim,kjm->ijm", ji, p, out=blocks[1])
        blocks[2] = blocks[1].transpose(1, 0, 2)
        np.einsum("kim,kjm->ijm", jj, p, out=blocks[3])
        we = np.einsum("ijm,jm->im", wm, e)
        grad = np.stack([np.einsum("kim,km->im", ji, we), np.einsum("kim,km->im", jj, we)])
        return self.system.assemble(blocks, grad)

    def step(self, data: F64, b: F64, damping: F64 | None) -> F64 | None:
        """Solve (H + diag(damping)) dx = -b; None when the factorization fails."""
        assert self.system is not None
        if damping is not None:
            data = data.copy()
            data[self.system.diag_slots] += damping
        if not self.chol.factor(self.system.matrix(data)):
            return None
        return -self.chol.solve(b)

    def apply(self, poses: F64, dx: F64) -> F64:
        """Additive update of the free vertices, heading wrapped."""
        assert self.system is not None
        out = poses + self.system.scatter(dx, poses.shape[0])
        out[:, 2] = wrap_angle(out[:, 2])
        return out


def optimize(graph: PoseGraph, cfg: OptimizerConfig = OptimizerConfig()) -> OptimizationResult:
    """Minimize the (robust) chi2 of a pose graph from its current estimate.

    Parameters
    ----------
    graph : PoseGraph
        Must be connected. ``graph.poses`` is the initial guess (see
        :mod:`algorithms.common.posegraph_init` for odometry and chordal initializations).
    cfg : OptimizerConfig

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
    return _run(_Problem(graph, cfg), graph.poses.copy(), cfg)


def _run(prob: _Problem, poses: F64, cfg: OptimizerConfig) -> OptimizationResult:
    c2, w, cost = prob.evaluate(poses)
    chi2_hist, cost_hist = [float(c2.sum())], [cost]
    best = (cost, poses, c2, w)
    status, iters, nfact = Status.MAX_ITERATIONS, 0, 0
    lam = cfg.lm_lambda
    if prob.system is None or cost == 0.0:
        status = Status.CONVERGED
    while status is Status.MAX_ITERATIONS and iters < cfg.max_iterations:
        iters += 1
        data, b = prob.normal_equations(poses, w)
        if cfg.method == "gn":
            dx = prob.step(data, b, None)
            nfact += 1
            if dx is None:
                status = Status.DIVERGED
                break
            new = prob.apply(poses, dx)
            c2n, wn, costn = prob.evaluate(new)
        else:
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
        if cost < best[0]:
            best = (cost, poses, c2, w)
        if cost > cfg.divergence_ratio * cost_hist[0]:
            status = Status.DIVERGED
        elif 0.0 <= rel < cfg.rel_tol or float(np.abs(dx).max(initial=0.0)) < cfg.step_tol:
            status = Status.CONVERGED
    _, poses, c2, w = best
    return OptimizationResult(
        poses=poses, status=status, iterations=iters, chi2_initial=chi2_hist[0], chi2_final=float(c2.sum()),
        chi2_history=np.array(chi2_hist), cost_history=np.array(cost_hist), edge_chi2=c2, weights=w,
        n_factorizations=nfact, linear_solver=prob.chol.backend, lm_lambda=lam,
    )
