"""Incremental (online) pose-graph optimization: add vertices and edges, re-optimize warm-started.

A new vertex is initialized by composing the first new edge that links it to a vertex already
placed. Updates that only extend the graph by such edges leave the optimum unchanged (each new
edge has zero error), so they cost no linear solve; updates carrying loop closures run a few
Gauss-Newton iterations from the current estimate on the whole graph.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slamreplay.algorithms.common.posegraph import OptimizerConfig, PoseGraph, Status, _Problem, _run, chi2
from slamreplay.algorithms.common.se2 import compose, inverse

F64 = NDArray[np.float64]


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
    """

    optimizer: OptimizerConfig = field(default_factory=lambda: OptimizerConfig(max_iterations=1, rel_tol=1e-5))
    reorder_growth: float = 0.1

    def __post_init__(self) -> None:
        if self.optimizer.gauge != 0:
            raise ValueError(f"optimizer.gauge must be 0 (vertex 0 is the gauge), got {self.optimizer.gauge}")
        if not self.reorder_growth >= 0.0:
            raise ValueError(f"reorder_growth must be >= 0, got {self.reorder_growth}")


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
        self._poses = p0[None, :].copy()
        self._i = np.zeros(0, dtype=np.int64)
        self._j = np.zeros(0, dtype=np.int64)
        self._z = np.zeros((0, 3))
        self._info = np.zeros((0, 3, 3))
        self._chi2 = 0.0
        self._order: NDArray[np.int64] | None = None  # block positions of vertices 1..n0-1
        self._order_n = 0

    @property
    def graph(self) -> PoseGraph:
        """The current graph and estimate (a validated copy)."""
        return PoseGraph(self._poses, self._i, self._j, self._z, self._info)

    @property
    def poses(self) -> F64:
        """Current estimate (n, 3), a copy."""
        return self._poses.copy()

    def set_poses(self, poses: ArrayLike) -> None:
        """Replace the estimate (n, 3) by one solved elsewhere (a robust batch solve); the gauge must not move."""
        p = np.array(poses, dtype=np.float64)
        if p.shape != self._poses.shape or not np.all(np.isfinite(p)):
            raise ValueError(f"poses must be finite with shape {self._poses.shape}, got {p.shape}")
        if not np.array_equal(p[0], self._poses[0]):
            raise ValueError("poses: vertex 0 is the gauge and must not move")
        self._poses = p
        self._chi2 = chi2(PoseGraph._trusted(self._poses, self._i, self._j, self._z, self._info))

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
        n = self._poses.shape[0]
        ii = np.asarray(i, dtype=np.int64).reshape(-1)
        jj = np.asarray(j, dtype=np.int64).reshape(-1)
        k = ii.size
        if k == 0:
            raise ValueError("i: an update needs at least one edge")
        top = int(max(ii.max(), jj.max())) + 1
        # validates the new edges (shapes, indices, information) on a graph with room for new vertices
        new = PoseGraph(np.zeros((max(top, n), 3)), ii, jj, np.asarray(measurements, dtype=np.float64),
                        np.asarray(information, dtype=np.float64))
        n_new = max(top - n, 0)
        poses = np.vstack([self._poses, np.full((n_new, 3), np.nan)])
        placed = np.r_[np.ones(n, dtype=bool), np.zeros(n_new, dtype=bool)]
        used = np.zeros(k, dtype=bool)
        progress = True
        while progress:  # loops over the few new edges of one update, not over the graph
            progress = False
            for e in np.flatnonzero(~used):
                a, b = int(ii[e]), int(jj[e])
                if placed[a] and not placed[b]:
                    poses[b] = compose(poses[a], new.measurements[e])
                elif placed[b] and not placed[a]:
                    poses[a] = compose(poses[b], inverse(new.measurements[e]))
                else:
                    continue
                placed[a] = placed[b] = used[e] = progress = True
        if not np.all(placed):
            v = int(np.flatnonzero(~placed)[0])
            raise ValueError(f"i, j: new vertex {v} is not linked to the graph by these edges")
        self._poses = poses
        self._i = np.r_[self._i, ii]
        self._j = np.r_[self._j, jj]
        self._z = np.concatenate([self._z, new.measurements])
        self._info = np.concatenate([self._info, new.information])
        closures = int(k - used.sum())
        iters = nfact = 0
        status = None
        if closures:
            g = PoseGraph._trusted(self._poses, self._i, self._j, self._z, self._info)
            nv = self._poses.shape[0]
            order = None
            if self._order is not None and nv - self._order_n <= self.cfg.reorder_growth * self._order_n:
                order = np.r_[self._order, np.arange(self._order.size, nv - 1)]
            prob = _Problem(g, self.cfg.optimizer, order=order, check_connected=False)
            if order is None and prob.system is not None:
                self._order, self._order_n = prob.system.pos[1:].copy(), nv
            res = _run(prob, self._poses.copy(), self.cfg.optimizer)
            self._poses, self._chi2 = res.poses, res.chi2_final
            iters, nfact, status = res.iterations, res.n_factorizations, res.status
        else:
            self._chi2 = float(self._chi2)  # new tree edges add zero error
        return UpdateResult(
            n_vertices=self._poses.shape[0], n_edges=self._i.size, new_vertices=n_new, new_edges=k,
            loop_closures=closures, iterations=iters, n_factorizations=nfact, chi2=self._chi2, status=status,
        )
