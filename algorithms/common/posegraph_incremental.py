"""Incremental (online) pose-graph optimization: add vertices and edges, re-optimize warm-started.

A new vertex is initialized by composing the first new edge that links it to a vertex already
placed. Updates that only extend the graph by such edges leave the optimum unchanged (each new
edge has zero error), so they cost no linear solve; updates carrying loop closures run a few
Gauss-Newton iterations from the current estimate on the whole graph.

With ``skip_chi2 > 0`` an update whose loop closures fit the current estimate well enough skips
that re-optimization (the relinearization-skipping idea of iSAM2 [1]_, with a bound instead of
iSAM2's per-variable threshold). At a least-squares optimum with information matrix
``Lambda``, adding measurements with residuals ``r`` and information ``Omega`` moves the
(linearized) optimum by ``delta`` with ``delta^T Lambda' delta <= r^T Omega r`` (``Lambda'`` the
information with them: ``delta = Lambda'^-1 J^T Omega r`` and ``J Lambda'^-1 J^T <= Omega^-1``).
So the skipped estimate stays within Mahalanobis distance ``sqrt(debt)`` of the re-optimized one,
where ``debt`` is the chi2 of the closures not yet solved plus ``b^T H^-1 b`` left after the last
Gauss-Newton step (its gradient solved with its own factorization: what a further step would
still move). An update re-optimizes when the debt exceeds ``skip_chi2``.

References
----------
.. [1] M. Kaess, H. Johannsson, R. Roberts, V. Ila, J. Leonard, F. Dellaert, "iSAM2: Incremental
   smoothing and mapping using the Bayes tree", IJRR 2012, sec. V (fluid relinearization).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common.posegraph import (
    OptimizerConfig,
    PoseGraph,
    Status,
    _checked_edges,
    _Problem,
    _run,
    chi2,
    edge_errors,
)
from slamreplay.algorithms.common.se2 import compose, inverse

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class IncrementalConfig:
    """Settings of :class:`IncrementalOptimizer`.

    Attributes
    ----------
    optimizer : used for each re-optimization (its kernel at its fixed parameter: no graduation,
        no inlier gate); its ``max_iterations`` is the per-update budget
        (default 1: one relinearization per update, as iSAM2 does; the next update continues from
        there, and M3500 replayed this way ends at the batch optimum).
    reorder_growth : recompute the fill-reducing ordering when the vertex count has grown by this
        fraction since it was last computed; in between, new vertices are ordered last.
    skip_chi2 : an update with loop closures re-optimizes only when the chi2 of the closures not
        yet solved, plus what the last Gauss-Newton step left (``b^T H^-1 b``), exceeds this; the
        estimate then stays within that Mahalanobis distance squared of the re-optimized one
        (module docstring). 0: re-optimize on every update with loop closures (exact mode).
    """

    optimizer: OptimizerConfig = field(default_factory=lambda: OptimizerConfig(max_iterations=1, rel_tol=1e-5))
    reorder_growth: float = 0.1
    skip_chi2: float = 1.0

    def __post_init__(self) -> None:
        if self.optimizer.gauge != 0:
            raise ValueError(f"optimizer.gauge must be 0 (vertex 0 is the gauge), got {self.optimizer.gauge}")
        if not self.reorder_growth >= 0.0:
            raise ValueError(f"reorder_growth must be >= 0, got {self.reorder_growth}")
        if not (self.skip_chi2 >= 0.0 and np.isfinite(self.skip_chi2)):
            raise ValueError(f"skip_chi2 must be finite and >= 0, got {self.skip_chi2}")


@dataclass(frozen=True, slots=True)
class UpdateResult:
    """What one :meth:`IncrementalOptimizer.step` did.

    Attributes
    ----------
    n_vertices, n_edges : graph size after the update.
    new_vertices, new_edges : added in this update.
    loop_closures : new edges that did not initialize a vertex (they trigger the re-optimization).
    iterations, n_factorizations : work of the re-optimization (0 when none was needed).
    chi2 : plain chi2 of the whole graph after the update.
    status : of the re-optimization; None when none ran.
    debt : bound on the squared Mahalanobis distance between the estimate and the re-optimized
        one (``skip_chi2``); 0 when ``skip_chi2`` is 0 (not tracked).
    """

    n_vertices: int
    n_edges: int
    new_vertices: int
    new_edges: int
    loop_closures: int
    iterations: int
    n_factorizations: int
    chi2: float
    status: Status | None
    debt: float = 0.0


def _compose1(a: F64, b: F64) -> tuple[float, float, float]:
    """se2.compose of one pose pair in scalar arithmetic (numpy's per-call overhead is most of the
    time of an update that skips the re-optimization)."""
    x, y, t = float(a[0]), float(a[1]), float(a[2])
    c, s = math.cos(t), math.sin(t)
    h = (t + float(b[2]) + math.pi) % (2.0 * math.pi) - math.pi
    if h >= math.pi:  # as se2.wrap_angle: [-pi, pi)
        h -= 2.0 * math.pi
    return x + c * float(b[0]) - s * float(b[1]), y + s * float(b[0]) + c * float(b[1]), h


class _Rows:
    """An array that grows by rows with doubling capacity: appending costs the new rows, not a copy of all."""

    def __init__(self, first: NDArray[np.generic]) -> None:
        self._buf = first.copy()
        self.n = first.shape[0]

    @property
    def view(self) -> NDArray[np.generic]:
        """The rows so far (a view: valid until the next append)."""
        return self._buf[: self.n]

    def room(self, k: int) -> NDArray[np.generic]:
        """The buffer, with room for k more rows (rows n.. n+k-1 are scratch until :meth:`grow`)."""
        if self.n + k > self._buf.shape[0]:
            bigger = np.empty((max(2 * self._buf.shape[0], self.n + k, 16), *self._buf.shape[1:]), self._buf.dtype)
            bigger[: self.n] = self._buf[: self.n]
            self._buf = bigger
        return self._buf

    def grow(self, rows: NDArray[np.generic]) -> None:
        """Append rows."""
        self.room(rows.shape[0])[self.n : self.n + rows.shape[0]] = rows
        self.n += rows.shape[0]


class IncrementalOptimizer:
    """Online 2D pose graph; vertex 0 (at ``first_pose``) is the gauge.

    Parameters
    ----------
    cfg : IncrementalConfig
    first_pose : (3,) pose of vertex 0 in the world frame.
    """

    def __init__(self, cfg: IncrementalConfig = IncrementalConfig(), first_pose: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        p0 = np.asarray(first_pose, dtype=np.float64)
        if p0.shape != (3,) or not np.all(np.isfinite(p0)):
            raise ValueError(f"first_pose must be a finite (3,) pose, got {p0!r}")
        self.cfg = cfg
        self._p = _Rows(p0[None, :])
        self._e = [_Rows(np.zeros(0, dtype=np.int64)), _Rows(np.zeros(0, dtype=np.int64)),
                   _Rows(np.zeros((0, 3))), _Rows(np.zeros((0, 3, 3)))]  # i, j, measurements, information
        self._chi2 = 0.0
        self._order: NDArray[np.int64] | None = None  # block positions of vertices 1..n0-1
        self._order_n = 0
        self._debt = 0.0  # skip_chi2: chi2 of unsolved closures + b^T H^-1 b after the last step

    def _arrays(self) -> tuple[F64, I64, I64, F64, F64]:
        """Views of the poses and the edge arrays (valid until the next append)."""
        i, j, z, f = (r.view for r in self._e)
        return cast(F64, self._p.view), cast(I64, i), cast(I64, j), cast(F64, z), cast(F64, f)

    def _trusted(self) -> PoseGraph:
        """The current graph on views of the buffers (no copy, no validation): for use within a step."""
        return PoseGraph._trusted(*self._arrays())

    @property
    def graph(self) -> PoseGraph:
        """The current graph and estimate (a validated copy)."""
        return PoseGraph(*self._arrays())

    @property
    def poses(self) -> F64:
        """Current estimate (n, 3), a copy."""
        return np.array(self._p.view, dtype=np.float64)

    def set_poses(self, poses: ArrayLike) -> None:
        """Replace the estimate (n, 3) by one solved elsewhere (a robust batch solve); the gauge must not move."""
        p = np.array(poses, dtype=np.float64)
        cur = self._p.view
        if p.shape != cur.shape or not np.all(np.isfinite(p)):
            raise ValueError(f"poses must be finite with shape {cur.shape}, got {p.shape}")
        if not np.array_equal(p[0], cur[0]):
            raise ValueError("poses: vertex 0 is the gauge and must not move")
        cur[:] = p
        self._chi2 = chi2(self._trusted())
        self._debt = np.inf if self.cfg.skip_chi2 > 0.0 else 0.0  # unknown: the next closure re-optimizes

    def step(self, i: ArrayLike, j: ArrayLike, measurements: ArrayLike, information: ArrayLike) -> UpdateResult:
        """Add edges (and the new vertices they reach), then re-optimize if they close loops.

        Parameters
        ----------
        i, j : (k,) int; new vertices must be numbered n, n+1, ... (n = current vertex count).
        measurements : (k, 3) pose of j in the frame of i.
        information : (k, 3, 3) symmetric positive-definite information matrices.

        Returns
        -------
        UpdateResult
        """
        n = self._p.n
        ii = np.asarray(i, dtype=np.int64).reshape(-1)
        jj = np.asarray(j, dtype=np.int64).reshape(-1)
        k = ii.size
        if k == 0:
            raise ValueError("i: an update needs at least one edge")
        top = int(max(ii.max(), jj.max())) + 1
        # validates the new edges (shapes, indices, information) on a graph with room for new vertices
        ii, jj, z_new, info_new = _checked_edges(ii, jj, measurements, information, max(top, n))
        n_new = max(top - n, 0)
        poses = self._p.room(n_new)  # rows n.. are filled as the new vertices are placed
        placed = np.zeros(n + n_new, dtype=bool)
        placed[:n] = True
        used = np.zeros(k, dtype=bool)
        progress = True
        while progress:  # loops over the few new edges of one update, not over the graph
            progress = False
            for e in np.flatnonzero(~used):
                a, b = int(ii[e]), int(jj[e])
                if placed[a] and not placed[b]:
                    poses[b] = _compose1(poses[a], z_new[e])
                elif placed[b] and not placed[a]:
                    poses[a] = compose(poses[b], inverse(z_new[e]))
                else:
                    continue
                placed[a] = placed[b] = used[e] = progress = True
        if not np.all(placed[n:]):
            v = n + int(np.flatnonzero(~placed[n:])[0])
            raise ValueError(f"i, j: new vertex {v} is not linked to the graph by these edges")
        self._p.n += n_new
        for rows, new in zip(self._e, (ii, jj, z_new, info_new), strict=True):
            rows.grow(new)
        closures = int(k - used.sum())
        iters = nfact = 0
        status = None
        skip = self.cfg.skip_chi2 > 0.0
        c2_loops = 0.0
        if closures and skip:
            loops = np.flatnonzero(~used)
            sub = PoseGraph._trusted(self._arrays()[0], ii[loops], jj[loops], z_new[loops], info_new[loops])
            err = edge_errors(sub)
            c2_loops = float(np.einsum("mi,mij,mj->", err, info_new[loops], err))
            self._debt += c2_loops
            skip = self._debt <= self.cfg.skip_chi2
        if closures and skip:
            self._chi2 += c2_loops  # the other edges keep their errors: no pose moved
        elif closures:
            g = self._trusted()
            nv = self._p.n
            order = None
            if self._order is not None and nv - self._order_n <= self.cfg.reorder_growth * self._order_n:
                order = np.r_[self._order, np.arange(self._order.size, nv - 1)]
            prob = _Problem(g, self.cfg.optimizer, order=order, check_connected=False)
            if order is None and prob.system is not None:
                self._order, self._order_n = prob.system.pos[1:].copy(), nv
            res = _run(prob, g.poses.copy(), self.cfg.optimizer)
            self._p.view[:] = res.poses
            self._chi2 = res.chi2_final
            iters, nfact, status = res.iterations, res.n_factorizations, res.status
            if self.cfg.skip_chi2 > 0.0 and (nfact == 0 or status is Status.DIVERGED):
                self._debt = np.inf  # nothing to measure the debt with: the next closure re-optimizes
            elif self.cfg.skip_chi2 > 0.0:
                self._debt = _remaining(prob, res.poses, res.weights)
        else:
            self._chi2 = float(self._chi2)  # new tree edges add zero error
        return UpdateResult(
            n_vertices=self._p.n, n_edges=self._e[0].n, new_vertices=n_new, new_edges=k,
            loop_closures=closures, iterations=iters, n_factorizations=nfact, chi2=self._chi2, status=status,
            debt=self._debt,
        )


def _remaining(prob: _Problem, poses: F64, w: F64) -> float:
    """``b^T H^-1 b`` at ``poses`` with the last factorization (of H one step earlier): what a further
    Gauss-Newton step would still move, in its own metric."""
    if prob.system is None:
        return 0.0
    b = prob.gradient(poses, w)
    return max(float(np.einsum("i,i->", b, prob.chol.solve(b))), 0.0)
